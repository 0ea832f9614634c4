"""``ndtom``: map ROS bags into NDT Occupancy Maps, inspect them, export the maps.

Commands: ``info`` (what is in a recording or a map file), ``map`` (recording -> map
file), ``demo`` (a built-in synthetic scene -> map file), ``export`` (map file -> PLY,
PCD, npz, CSV, OctoMap .bt or a 2-D occupancy grid). The work is done by :mod:`ndtom_ti.pipeline` and :mod:`ndtom_ti.export`;
this module parses options, shows progress and tables, and turns errors into one red
line and a hint.

Exit codes: 0 done; 1 failed (the memory budget or a bad scan stopped mapping: what was
mapped is saved; or the map could not be written; or an internal error); 2 bad input or
usage (unreadable recording, missing topic or poses, bad option or config file, output
path that cannot be written); 130 interrupted by Ctrl-C, 143 by SIGTERM (what was mapped
is saved).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import signal
import tempfile
import time
from collections.abc import Iterator
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text
from rich.tree import Tree

from . import __version__
from .io import RecordingError
from .mapfile import MapFileError
from .runtime import MapMemoryError

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

MAP_SUFFIX = ".ndtom"
_OWN_PROCESS = False  # main() runs the command in a process of its own (not in a test runner)
_MAGIC = b"NDTOMTI\n"

app = typer.Typer(
    name="ndtom",
    help="Exact NDT Occupancy Maps from ROS bags (Taichi, CPU or CUDA).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


class Arch(str, Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


class MissModel(str, Enum):
    ndt = "ndt"
    paper = "paper"


class Format(str, Enum):
    ply = "ply"
    pcd = "pcd"
    npz = "npz"
    csv = "csv"
    bt = "bt"
    grid = "grid"


# ---------------------------------------------------------------------------- output helpers
def _out() -> Console:
    return Console(highlight=False)


def _err() -> Console:
    return Console(stderr=True, highlight=False, soft_wrap=True)


def _fail(message: str, hint: str | None = None, code: int = EXIT_USAGE) -> NoReturn:
    err = _err()
    err.print(Text.assemble(("Error: ", "bold red"), (message, "red")))
    if hint:
        err.print(Text.assemble(("Hint: ", "bold"), hint))
    raise typer.Exit(code)


def _need_extra(module: str, purpose: str, code: int = EXIT_FAILURE) -> None:
    """Stop before any work when an optional package is missing, naming its extra and
    how to install it."""
    from .extras import available, extra_of, install_hint, missing_message

    if not available(module):
        _fail(missing_message(module, purpose), f"install it with: {install_hint(extra_of(module))}", code)


def _without_extra(module: str, skipped: str) -> bool:
    """True (after a note saying what is skipped and how to get it) when ``module`` is missing."""
    from .extras import available, extra_of, install_hint

    if available(module):
        return False
    _err().print(Text(f"note: {module} is not installed (extra [{extra_of(module)}]): {skipped}; to get it: "
                      f"{install_hint(extra_of(module))}", style="yellow"), soft_wrap=True)
    return True


_MEMORY_HINT = ("use a coarser resolution (-r), a smaller --max-range, fewer scans (--every, --max-scans), "
                "or a CUDA device (--arch cuda)")


def _memory_refusal(summary: Any, saved: str) -> tuple[str, str]:
    """The error and hint of a scan the memory budget refused, in `ndtom map`'s options."""
    from . import hostpool, runtime

    budget = runtime.pool_limit() / 2**30
    scan = summary.scans_used + 1
    error = (f"scan {scan} was refused: it could take Taichi's memory pool past its {budget:.2f} GiB budget "
             f"(--memory-limit); nothing of it was mapped")
    ways = []
    note = runtime.pool_note()
    if runtime.current_arch() == "cpu" and note is None:
        most = 0.8 * hostpool.physical_memory() / 2**30
        if most > budget * 1.1:
            ways.append(f"a larger --memory-limit (this machine has {hostpool.physical_memory() / 2**30:.0f} GiB; "
                        f"e.g. --memory-limit {most:.0f})")
    elif note is not None:
        ways.append(f"(--memory-limit cannot go past ~0.94 GiB here: {note})")
    ways += [f"a coarser resolution (-r {2 * summary.resolution:g})",
             "a smaller --max-range (long rays at a fine resolution touch the most cells)"]
    if runtime.current_arch() == "cpu":
        ways.append("a CUDA device (--arch cuda)")
    more = " Or map a part: --max-scans N or --end T stops before it." if summary.scans_used else ""
    return error, f"{saved} To map scan {scan}, use " + ", ".join(ways[:-1]) + f", or {ways[-1]}." + more


@contextlib.contextmanager
def _user_errors(*, recording: str | None = None, map_file: str | None = None) -> Iterator[None]:
    """Turn the errors a user can cause into one red line + hint and an exit code."""
    try:
        yield
    except (typer.Exit, typer.Abort, SystemExit):
        raise
    except RecordingError as exc:
        _fail(str(exc), recording or "`ndtom info BAG` shows the topics, TF frames and pose sources of a recording")
    except MapFileError as exc:
        _fail(str(exc), map_file or "give a map file written by `ndtom map` or `ndtom demo`")
    except MapMemoryError as exc:
        _fail(str(exc), _MEMORY_HINT, EXIT_FAILURE)
    except FileNotFoundError as exc:
        _fail(str(exc), map_file or "check the path")
    except OSError as exc:
        _fail(f"{exc}", "check the path and its permissions", EXIT_FAILURE)
    except (ValueError, TypeError) as exc:
        _fail(str(exc), "`ndtom COMMAND --help` lists the options and their ranges")
    except KeyboardInterrupt as exc:
        from .pipeline import signal_name

        signum = getattr(exc, "signum", signal.SIGINT)
        _fail(f"interrupted ({signal_name(signum)}); nothing was written", None, 128 + signum)
    except Exception as exc:  # the last line of defence: no traceback for users
        if os.environ.get("NDTOM_DEBUG"):
            raise
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        text = lines[0] if len(lines) == 1 else (f"{lines[0]} ... {lines[-1]}" if lines else "")
        _fail(f"internal error: {type(exc).__name__}: {text}",
              "set NDTOM_DEBUG=1 to see the traceback, and please report it", EXIT_FAILURE)


def _init(arch: Arch, memory_limit: float | None = None) -> str:
    """Initialise Taichi once (its start-up line is not shown); a wrong arch is a usage
    error. Why the CPU memory budget is below the one asked for is shown as a note."""
    import warnings

    import ndtom_ti

    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            used = ndtom_ti.init(arch.value, memory_limit_GB=memory_limit, pin_threads=_pin_threads())
        except RuntimeError as exc:
            _fail(str(exc), "use --arch cpu (or auto)")
        except ValueError as exc:
            if memory_limit is None:
                raise
            _fail(str(exc).replace("memory_limit_GB=", "--memory-limit ").replace("memory_limit_GB", "--memory-limit"),
                  "give --memory-limit in GiB, below the machine's memory")
    for w in caught:
        if issubclass(w.category, RuntimeWarning) and w.message is not None:
            _err().print(Text(f"note: {w.message}", style="dim"))
    return used


def _check_writable(path: Path, what: str = "output") -> Path:
    """Fail now (before any mapping) when ``path`` cannot be written."""
    path = path.expanduser()
    if path.is_dir():
        _fail(f"the {what} path {path} is a folder", f"give a file name, e.g. {path / ('map' + MAP_SUFFIX)}")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.exists():
        _fail(f"cannot write the {what} {path}: folder {folder} does not exist", "create the folder first or choose "
              "another path with -o")
    if not folder.is_dir():
        _fail(f"cannot write the {what} {path}: {folder} is not a folder", "choose another path with -o")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".check", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        _fail(f"cannot write the {what} {path}: {exc.strerror or exc}", "choose a writable folder with -o")
    if path.exists() and not path.is_file():
        _fail(f"cannot write the {what} {path}: it exists and is not a regular file", "choose another path with -o")
    return path


def _mib(b: float) -> str:
    return f"{b / 2**20:.1f} MiB"


def _count(n: int) -> str:
    return f"{n:,}"


def _secs(ns: int | None, start_ns: int | None = None) -> str:
    """Seconds; relative to the bag start (record time) when ``start_ns`` is given and near."""
    if ns is None:
        return "-"
    if start_ns is not None and abs(ns - start_ns) < 86_400 * 10**9:
        return f"{(ns - start_ns) / 1e9:.3f}"
    return f"{ns / 1e9:.3f} (absolute)"


def _table(title: str, *columns: str, header: bool = True) -> Table:
    t = Table(title=title, show_header=header, title_justify="left")
    for i, col in enumerate(columns):
        t.add_column(col, overflow="fold", style="bold" if (not header and i == 0) else None,
                     justify="right" if col in ("messages", "poses") else "left")
    return t


# ---------------------------------------------------------------------------- version
def _version(value: bool) -> None:
    if value:
        print(f"ndtom_ti {__version__}")
        raise typer.Exit()


_PIN = {"threads": True}


def _pin_threads() -> bool:
    """The command pins Taichi's CPU workers (affinity.py) unless --no-pin-threads or
    NDTOM_PIN_THREADS=0 says not to."""
    return _PIN["threads"] and os.environ.get("NDTOM_PIN_THREADS", "1") not in ("0", "")


@app.callback()
def _main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Show the version and exit.")] = False,
    pin_threads: Annotated[bool, typer.Option(
        "--pin-threads/--no-pin-threads", help="Fix each of Taichi's CPU worker threads to a CPU of its own "
        "(faster short loops; off leaves them to the scheduler, e.g. on CPUs shared with busy drivers).")] = True,
) -> None:
    """Exact NDT Occupancy Maps from ROS bags (Taichi, CPU or CUDA).

    Exit codes: 0 ok, 1 failed (e.g. memory budget; what was mapped is saved), 2 bad
    input or usage, 130 interrupted by Ctrl-C, 143 by SIGTERM (what was mapped is saved).
    """
    _PIN["threads"] = pin_threads


# ---------------------------------------------------------------------------- info
def _info_map(path: Path) -> None:
    from .mapfile import read_header

    h = read_header(path)
    out = _out()
    t = _table(f"Map file {path}", "", "", header=False)
    md = h.get("metadata") or {}
    t.add_row("format version", str(h.get("version")))
    t.add_row("resolution", f"{h.get('resolution')} m")
    t.add_row("occupancy", str(h.get("occupancy")))
    t.add_row("scans inserted", _count(int(h.get("scans_inserted", 0))))
    t.add_row("points inserted", _count(int(h.get("points_inserted", 0))))
    arrays = {a["name"]: a["shape"] for a in h.get("arrays", [])}
    if "g_index" in arrays:
        t.add_row("Gaussian records", _count(arrays["g_index"][0]))
    if "occ_index" in arrays:
        t.add_row("known cells", _count(arrays["occ_index"][0]))
    for key in ("source", "cloud_topic", "pose_source", "ndtom_ti_version", "created", "complete"):
        if key in md:
            t.add_row(key.replace("_", " "), escape(str(md[key])))
    # max_range is stored as null when there is no limit
    t.add_row("config", escape(", ".join(f"{k}={'inf' if k == 'max_range' and v is None else v}"
                                         for k, v in (h.get("config") or {}).items())))
    out.print(t)


def _info_recording(path: Path) -> None:
    from .io import open_recording

    with open_recording(path) as rec:
        info = rec.info()
    out = _out()
    head = _table(f"Recording {info.path}", "", "", header=False)
    head.add_row("format", f"{info.format.upper()} ({info.storage})")
    head.add_row("messages", _count(info.message_count))
    head.add_row("duration", f"{info.duration_s:.3f} s")
    head.add_row("start / end", f"{info.start_ns / 1e9:.3f} / {info.end_ns / 1e9:.3f} s (record time; times "
                 "below are seconds from the start)")
    out.print(head)

    pose_topics = {s.name for s in info.pose_sources if s.kind == "topic"}
    topics = _table("Topics", "topic", "type", "messages", "rate", "use")
    for ts in info.topics:
        if ts.name in info.cloud_frames:
            use = f"mappable (frame {info.cloud_frames[ts.name]})"
        elif ts.name in info.mappable_topics:
            use = "mappable"
        elif ts.msgtype in ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"):
            use = "TF"
        elif ts.name in pose_topics:
            use = "poses"
        else:
            use = ""
        rate = f"{(ts.count - 1) / info.duration_s:.1f} Hz" if ts.count > 1 and info.duration_s > 0 else "-"
        topics.add_row(escape(ts.name), ts.msgtype, _count(ts.count), rate, escape(use))
    if not info.topics:
        topics.add_row("(none: the recording is empty)", "", "", "", "")
    out.print(topics)

    if info.tf_frames:
        edges = {e.child: e for e in info.tf_edges}
        children: dict[str, list[str]] = {}
        for child, parent in info.tf_tree.items():
            children.setdefault(parent, []).append(child)
        roots = [f for f in info.tf_frames if f not in info.tf_tree]
        tree = Tree(f"TF frames ({len(info.tf_frames)})")

        def add(node: Tree, frame: str) -> None:
            for child in sorted(children.get(frame, [])):
                e = edges.get(child)
                if e is None:
                    label = child
                elif e.static:
                    label = f"{child}  [static]"
                else:
                    label = (f"{child}  [{e.count} transforms, {_secs(e.first_ns, info.start_ns)} .. "
                             f"{_secs(e.last_ns, info.start_ns)} s]")
                add(node.add(escape(label)), child)

        for root in roots:
            add(tree.add(escape(root)), root)
        out.print(tree)
    else:
        out.print("TF frames: none (no /tf or /tf_static)")

    ps = _table("Pose sources", "kind", "source", "parent -> child", "poses", "time span (s)", "note")
    for s in info.pose_sources:
        span = ("static" if s.first_ns is None else
                f"{_secs(s.first_ns, info.start_ns)} .. {_secs(s.last_ns, info.start_ns)}")
        note = "constant (not a trajectory)" if s.constant and s.count > 1 else ""
        ps.add_row(s.kind, escape(s.name), escape(f"{s.parent_frame} -> {s.child_frame or '?'}"),
                   _count(s.count), span, note)
    if not info.pose_sources:
        ps.add_row("-", "(none)", "", "", "", "")
    out.print(ps)

    m = _table("Mapping", "", "", header=False)
    m.add_row("mappable topics", escape(", ".join(info.mappable_topics) or "(none)"))
    if info.default_cloud_topic:
        m.add_row("cloud topic", escape(info.default_cloud_topic))
    if info.pose_source:
        m.add_row("poses", escape(info.pose_source))
    out.print(m)
    if info.pose_error:
        out.print(Text.assemble(("Cannot map with the defaults: ", "bold yellow"), (info.pose_error, "yellow")),
                  soft_wrap=True)
    elif info.default_cloud_topic:
        out.print(Text(f"Ready: ndtom map {path} -r 0.2", style="green"), soft_wrap=True)
    for note in info.notes:
        out.print(Text(f"note: {note}", style="dim"), soft_wrap=True)


@app.command(short_help="What a recording (topics, TF tree, poses) or a map file holds.")
def info(
    path: Annotated[Path, typer.Argument(metavar="PATH", help="A ROS1 .bag file, a ROS2 bag folder, or an .ndtom map file.",
                                         show_default=False)],
) -> None:
    """Show what is in a recording: topics, types, counts, duration, the TF tree, which
    topics can be mapped and which pose sources exist. Given a map file, show its header."""
    with _user_errors():
        if path.is_file():
            with path.open("rb") as fh:
                is_map = fh.read(len(_MAGIC)) == _MAGIC
            if is_map:
                _info_map(path)
                return
        _info_recording(path)


# ---------------------------------------------------------------------------- map
def default_output(bag: Path) -> Path:
    """The map path used without -o: the recording's name with .ndtom, in the current folder."""
    name = bag.expanduser().resolve().name if bag.name in ("", ".", "..") else bag.name
    stem = name.removesuffix(".bag")
    return Path.cwd() / (stem + MAP_SUFFIX)


class _Bar:
    """Progress callback for the pipeline: a rich progress bar on stderr (scans, points/s)."""

    def __init__(self, arch: Arch, show: bool, memory_limit: float | None = None) -> None:
        self.arch = arch
        self.memory_limit = memory_limit
        self.show = show
        self.progress: Progress | None = None
        self.task: Any = None
        self.arch_used = ""

    def __call__(self, summary: Any, report: Any) -> None:
        if report is None:  # the recording is fine: start Taichi and the bar
            self.arch_used = _init(self.arch, self.memory_limit)
            err = _err()
            err.print(Text(f"Mapping {summary.cloud_topic or summary.source} at {summary.resolution:g} m on "
                           f"{self.arch_used}; poses: {summary.pose_source or '-'}", style="cyan"))
            if self.show:
                self.progress = Progress(
                    TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("scans"), TextColumn("{task.fields[rate]}"), TimeElapsedColumn(),
                    console=Console(stderr=True), transient=False,
                )
                self.task = self.progress.add_task("mapping", total=summary.scans_expected, rate="")
                self.progress.start()
            return
        if self.progress is not None:
            rate = f"{summary.points_per_second / 1e6:.2f} M points/s"
            total = summary.scans_expected
            if total is not None and summary.scans_used > total:
                total = summary.scans_used
            self.progress.update(self.task, completed=summary.scans_used, total=total, rate=rate)

    def stop(self, summary: Any | None = None) -> None:
        if self.progress is not None:
            if summary is not None:
                self.progress.update(self.task, completed=summary.scans_used, total=summary.scans_used
                                     if summary.complete else self.progress.tasks[0].total)
            self.progress.stop()
            self.progress = None


# Why clouds were not mapped, in words (the pipeline's reasons are short keys).
_SKIP_WORDS = {"every": "left out by --every", "every_distance": "left out by --every-distance (sensor moved less)"}


def _skip_reason(reason: str) -> str:
    return _SKIP_WORDS.get(reason, reason)


def _summary_table(summary: Any, output: Path | None) -> Table:
    t = _table("Mapping summary", "", "", header=False)
    t.add_row("source", escape(summary.source))
    if summary.cloud_topic:
        t.add_row("cloud topic", escape(f"{summary.cloud_topic} (frame {summary.frame_id})"))
    if summary.pose_source:
        t.add_row("poses", escape(summary.pose_source))
        t.add_row("map frame", escape(str(summary.fixed_frame)))
    t.add_row("resolution", f"{summary.resolution:g} m" + ("" if summary.occupancy else " (no occupancy)"))
    t.add_row("scans used", f"{_count(summary.scans_used)} of {_count(summary.clouds_seen)} clouds read")
    skipped = ", ".join(f"{_count(n)} {_skip_reason(reason)}" for reason, n in summary.skipped.items()) or "none"
    t.add_row("scans skipped", escape(skipped))
    t.add_row("points", f"{_count(summary.points_in)} in, {_count(summary.points_used)} inserted"
              + (f", {_count(summary.free_rays)} free rays" if summary.free_rays else ""))
    d = summary.dropped
    t.add_row("points dropped", f"{_count(d['nonfinite'])} not finite, {_count(d['range'])} out of range, "
              f"{_count(d['outside_grid'])} outside the grid")
    t.add_row("Gaussians", _count(summary.gaussians))
    t.add_row("known cells", _count(summary.known_cells))
    t.add_row("memory", f"{_mib(summary.memory_bytes)} map; Taichi pool {_mib(summary.pool_bytes)} of "
              f"{_mib(summary.pool_budget_bytes)}")
    if summary.scan_seconds:
        t.add_row("time per scan", f"median {summary.ms_per_scan_median:.1f} ms, p95 {summary.ms_per_scan_p95:.1f} ms"
                  f" (first scan {summary.ms_first_scan:.0f} ms, kernels compiled)")  # fmt: skip
    t.add_row("total", f"{summary.wall_seconds:.2f} s ({summary.points_per_second / 1e6:.2f} M points/s)")
    if output is not None:
        t.add_row("map file", escape(str(output)))
    return t


def _finish_mapping(m: Any, summary: Any, output: Path, bar: _Bar, extra_rows: list | None = None,
                    signals: Any = None) -> int:
    """Print the summary, write the map (also after Ctrl-C, SIGTERM, a memory stop or a bad
    scan), return the exit code. ``signals``: the command's StopSignals; from here on a
    signal only waits for the map to be on disk."""
    if signals is not None:
        signals.phase = "saving"
    bar.stop(summary)
    out, err = _out(), _err()
    wrote: Path | None = None
    if summary.scans_used:
        m.metadata.setdefault("options", {})["arch"] = bar.arch_used
        try:
            wrote = m.save(output)
        except OSError as exc:
            out.print(_summary_table(summary, None))
            _fail(f"cannot write the map to {output}: {exc}", "choose another path with -o", EXIT_FAILURE)
    out.print(_summary_table(summary, wrote))
    for row in extra_rows or []:
        out.print(row)
    for note in summary.skip_notes:
        err.print(Text(f"note: {note}", style="dim"))
    if summary.stopped == "interrupted":
        name = signals.name if signals is not None and signals.count else "Ctrl-C"
        n = summary.scans_used
        msg = (f"Interrupted: saved the {n} scan{'s' if n != 1 else ''} mapped so far to {wrote} ({name}; the map is "
               "marked incomplete)" if wrote else f"Interrupted ({name}) before any scan was mapped; no map written")
        err.print(Text(msg, style="bold yellow"))
        return signals.exit_code if signals is not None and signals.count else EXIT_INTERRUPTED
    if summary.stopped == "memory":
        saved = (f"Saved the {summary.scans_used} scans mapped before it to {wrote} (marked incomplete)." if wrote
                 else "Nothing was mapped; no map written.")
        error, hint = _memory_refusal(summary, saved)
        err.print(Text.assemble(("Error: ", "bold red"), (error, "red")))
        err.print(Text.assemble(("Hint: ", "bold"), hint))
        return EXIT_FAILURE
    if summary.stopped == "error":
        err.print(Text.assemble(("Error: ", "bold red"), (summary.error or "a scan could not be mapped", "red")))
        saved = (f"Saved the {summary.scans_used} scans mapped before it to {wrote} (marked incomplete)." if wrote
                 else "Nothing was mapped; no map written.")
        fix = ("Check that scan's pose and cloud (`ndtom info BAG`), or end the run before it with --end or "
               "--max-scans.")
        err.print(Text.assemble(("Hint: ", "bold"), f"{saved} {fix}"))
        return EXIT_FAILURE
    if not summary.scans_used:
        why = ", ".join(f"{n} {_skip_reason(r)}" for r, n in summary.skipped.items()) or "the selection is empty"
        _fail(f"no scans were mapped ({summary.clouds_seen} clouds: {why}); no map written",
              "check --start/--end/--every and the pose source (`ndtom info BAG`)")
    assert wrote is not None  # scans were mapped, so the map was written (or _fail above)
    out.print(Text(f"Map written to {wrote} ({_mib(wrote.stat().st_size)})", style="green"), soft_wrap=True)
    return EXIT_OK


@app.command("map", short_help="Map a recording (ROS1 bag or ROS2 folder) into a map file.")
def map_(
    bag: Annotated[Path, typer.Argument(metavar="BAG", help="A ROS1 .bag file or a ROS2 bag folder (sqlite3 or mcap).",
                                        show_default=False)],
    resolution: Annotated[float, typer.Option("-r", "--resolution", help="Cell size in metres.",
                                              show_default=False)],
    output: Annotated[Path | None, typer.Option(
        "-o", "--output", help="Map file to write (atomically). Default: the recording's name with .ndtom, "
        "in the current folder (site.bag -> ./site.ndtom).", show_default=False)] = None,
    cloud_topic: Annotated[str | None, typer.Option(
        help="PointCloud2 (or depth image) topic; needed only when the recording has several.")] = None,
    fixed_frame: Annotated[str | None, typer.Option(
        help="Frame of the map; default: the root of the cloud frame's TF tree.")] = None,
    poses: Annotated[Path | None, typer.Option(
        help="Pose file (TUM: t tx ty tz qx qy qz qw, or KITTI 3x4 rows) giving T_world_sensor.")] = None,
    pose_topic: Annotated[str | None, typer.Option(
        help="Pose topic (Odometry, PoseStamped, ...) to use instead of TF.")] = None,
    sensor_frame: Annotated[bool, typer.Option(
        "--sensor-frame", help="No poses: map every scan in the sensor frame (identity poses).")] = False,
    every: Annotated[int, typer.Option(min=1, help="Keep every N-th cloud.")] = 1,
    every_distance: Annotated[float | None, typer.Option(
        min=0.0, help="Keep a cloud once the sensor moved this far (m) from the last kept one.")] = None,
    start: Annotated[float | None, typer.Option(help="Skip clouds before this time (s from the bag start).")] = None,
    end: Annotated[float | None, typer.Option(help="Skip clouds after this time (s from the bag start).")] = None,
    max_scans: Annotated[int | None, typer.Option(min=1, help="Stop after this many scans.")] = None,
    max_range: Annotated[float | None, typer.Option(help="Drop points farther than this (m).")] = None,
    min_range: Annotated[float | None, typer.Option(help="Drop points closer than this (m).")] = None,
    occupancy: Annotated[bool, typer.Option(
        "--occupancy/--no-occupancy", help="Ray-trace free space (NDT-OM); --no-occupancy: Gaussians only.")] = True,
    miss_model: Annotated[MissModel | None, typer.Option(
        "--miss-model", help="How rays lower cells holding a Gaussian: ndt (by how squarely they pass it, "
        "IJRR 2013) or paper (a constant per ray, eq. 12). Default: the config's.")] = None,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
    memory_limit: Annotated[float | None, typer.Option(
        "--memory-limit", metavar="GIB", help="Memory budget of the map's sparse cells (GiB of Taichi's pool). "
        "Default: half of the machine's memory on the CPU, 90% of the device pool on CUDA.")] = None,
    config: Annotated[Path | None, typer.Option(
        help="JSON or TOML file of MapConfig options (p_occupied, p_empty, logodds_min, logodds_max, "
        "min_points, min_range, max_range, max_range_mode, n_max, miss_model, sigma_s, eta); -r, --min-range, "
        "--max-range, --miss-model win.")] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
    view: Annotated[bool, typer.Option(
        "--view", help="Map live in the browser viewer, at the recording's own rate, starting when a browser "
        "connects; the map is saved at the end and on Ctrl-C or SIGTERM.")] = False,
    host: Annotated[str, typer.Option(help="Viewer host (with --view).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Viewer port (with --view).")] = 8080,
    rate: Annotated[str, typer.Option(
        help="With --view: playback speed, times the recording's rate (1: as recorded, 2: twice as fast, "
        "max: as fast as mapping goes).")] = "1",
    no_wait: Annotated[bool, typer.Option(
        "--no-wait", help="With --view: start mapping at once, not when the first browser connects.")] = False,
) -> None:
    """Map a recording into an NDT Occupancy Map file.

    Prints a progress bar, then a summary (scans used and skipped and why, points,
    Gaussians, memory, time per scan). Ctrl-C (or SIGTERM) stops after the current scan
    and saves what was mapped (exit 130, or 143).
    """
    from .pipeline import load_config_file, map_recording, stop_signals

    code = EXIT_OK
    with _user_errors():
        if not (math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"-r/--resolution must be a positive number of metres, got {resolution}")
        given = [n for n, v in (("--poses", poses), ("--pose-topic", pose_topic), ("--sensor-frame", sensor_frame))
                 if v]
        if len(given) > 1:
            raise ValueError(f"give one pose source, not {' and '.join(given)}")
        if every > 1 and every_distance is not None:
            raise ValueError("give --every or --every-distance, not both")
        if start is not None and end is not None and end < start:
            raise ValueError(f"--end ({end}) is before --start ({start})")
        if memory_limit is not None:
            from .hostpool import physical_memory

            if not (math.isfinite(memory_limit) and memory_limit > 0):
                raise ValueError(f"--memory-limit must be a positive number of GiB, got {memory_limit}")
            if memory_limit * 2**30 > physical_memory():
                raise ValueError(f"--memory-limit {memory_limit:g} GiB is more than this machine's "
                                 f"{physical_memory() / 2**30:.1f} GiB of memory")
        cfg = load_config_file(config) if config is not None else None
        from .pipeline import config_with_ranges

        mapcfg = config_with_ranges(cfg, min_range=min_range, max_range=max_range,
                                    miss_model=miss_model.value if miss_model else None)  # fmt: skip
        out_path = _check_writable(output if output is not None else default_output(bag), "map file")
        if view:
            _need_extra("viser", "the live viewer (--view)")
            from .viewer.cli import live_recording_command, parse_rate

            speed = parse_rate(rate)
            _init(arch, memory_limit)
            bar = _Bar(arch, progress, memory_limit)
            try:
                code = live_recording_command(
                    bag, resolution, scan_options={
                        "cloud_topic": cloud_topic, "fixed_frame": fixed_frame, "pose_topic": pose_topic,
                        "poses_file": poses, "sensor_frame_only": sensor_frame, "every": every,
                        "every_distance": every_distance, "t_start": start, "t_end": end, "max_scans": max_scans},
                    occupancy=occupancy, config=mapcfg, host=host, port=port, speed=speed, wait_for_browser=not no_wait,
                    metadata={"command": "ndtom map --view", "config_file": str(config.resolve()) if config else None},
                    progress=bar, finish=lambda m, summary: _finish_mapping(m, summary, out_path, bar),
                )  # fmt: skip
            finally:
                bar.stop()
            raise typer.Exit(code)

        bar = _Bar(arch, progress, memory_limit)
        # Ctrl-C and SIGTERM: finish the scan in hand, save, then exit
        with stop_signals(restore=not _OWN_PROCESS) as sig:
            try:
                m, summary = map_recording(
                    bag, resolution, cloud_topic=cloud_topic, fixed_frame=fixed_frame, pose_topic=pose_topic,
                    poses_file=poses, sensor_frame_only=sensor_frame, every=every, every_distance=every_distance,
                    t_start=start, t_end=end, max_scans=max_scans, occupancy=occupancy, config=mapcfg,
                    metadata={"command": "ndtom map", "config_file": str(config.resolve()) if config else None},
                    progress=bar,
                )  # fmt: skip
            except BaseException:
                bar.stop()
                raise
            code = _finish_mapping(m, summary, out_path, bar, signals=sig)
            del m
    raise typer.Exit(code)


# ---------------------------------------------------------------------------- demo
@app.command(short_help="Map a built-in synthetic room; check it against the truth.")
def demo(
    out: Annotated[Path, typer.Option("--out", help="Folder for the map (created if missing).")] = Path("ndtom_demo"),
    resolution: Annotated[float, typer.Option("-r", "--resolution", help="Cell size in metres.")] = 0.2,
    scans: Annotated[int, typer.Option(min=2, max=1000, help="Number of scans.")] = 20,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
    view: Annotated[bool, typer.Option(
        "--view", help="Map the room live in the browser viewer (starting when a browser connects); writes the "
        "map too.")] = False,
    port: Annotated[int, typer.Option(help="Viewer port (with --view).")] = 8080,
    rate: Annotated[str, typer.Option(
        help="With --view: playback speed, times the scans' rate (1: 10 scans/s as recorded, max: as fast as "
        "mapping goes).")] = "1",
    no_wait: Annotated[bool, typer.Option(
        "--no-wait", help="With --view: start mapping at once, not when the first browser connects.")] = False,
) -> None:
    """Map a built-in synthetic room (walls, floor, boxes, one box that is taken away
    halfway) and check the map against the exact ground truth. Writes OUT/demo.ndtom."""
    from . import demo as demo_scene
    from .pipeline import map_scans, stop_signals

    code = EXIT_OK
    with _user_errors():
        if not (math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"-r/--resolution must be a positive number of metres, got {resolution}")
        if view:
            _need_extra("viser", "the live viewer (--view)")
        out = out.expanduser()
        if out.exists() and not out.is_dir():
            _fail(f"--out {out} is a file, not a folder", "give a folder for the demo's output")
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            _fail(f"cannot create the folder {out}: {exc.strerror or exc}", "choose another folder with --out")
        out_path = _check_writable(out / ("demo" + MAP_SUFFIX), "map file")
        scene = demo_scene.Scene()
        t0 = time.perf_counter()
        data = demo_scene.make_scans(scans, scene=scene)
        _err().print(Text(f"Demo scene: a 12 x 8 m room, {len(scene.boxes)} boxes (one taken away after scan "
                          f"{scene.vanishing[0].present_until}), {len(data)} lidar scans of about "
                          f"{sum(len(s.points) for s in data) // len(data):,} points, made in "
                          f"{time.perf_counter() - t0:.1f} s", style="cyan"))
        if view:
            from .viewer.cli import live_demo_command, parse_rate

            speed = parse_rate(rate)
            _init(arch)
            bar = _Bar(arch, progress)
            try:
                code = live_demo_command(
                    "127.0.0.1", port, resolution=resolution, n_scans=scans, scans=data, speed=speed,
                    wait_for_browser=not no_wait, progress=bar,
                    metadata={"command": "ndtom demo --view", "demo": {"scans": scans, "scene": "room 12x8x3 m, 5 boxes"}},
                    finish=lambda m, summary: _finish_mapping(m, summary, out_path, bar),
                )  # fmt: skip
            finally:
                bar.stop()
            raise typer.Exit(code)
        bar = _Bar(arch, progress)
        with stop_signals(restore=not _OWN_PROCESS) as sig:  # as in `ndtom map`
            try:
                m, summary = map_scans(
                    data, resolution, source="ndtom demo (synthetic room)", scans_expected=len(data),
                    pose_source="exact (synthetic)", fixed_frame="world",
                    metadata={"command": "ndtom demo", "demo": {"scans": scans, "scene": "room 12x8x3 m, 5 boxes"}},
                    progress=bar,
                )
            except BaseException:
                bar.stop()
                raise
            check = demo_scene.ground_truth_check(m.gaussians(), resolution, scene)
            m.metadata["ground_truth_check"] = check
            gt = _table("Against the ground truth", "", "", header=False)
            gt.add_row("Gaussians on a true surface", f"{check['on_surface'] * 100:.1f}% (mean within "
                       f"{resolution / 4:g} m)")
            gt.add_row("median distance to surface", f"{check['median_distance'] * 1000:.1f} mm")
            gt.add_row("left where the box was taken away", str(check["left_in_vanished"]))
            code = _finish_mapping(m, summary, out_path, bar, [gt], signals=sig)
            del m
        if code == EXIT_OK:
            _out().print(f"Next: ndtom export {out_path} --format ply", soft_wrap=True, markup=False)
    raise typer.Exit(code)


# ---------------------------------------------------------------------------- sweep
@app.command(short_help="Time per scan against resolution, beside OctoMap (Fig. 5).")
def sweep(
    bag: Annotated[Path | None, typer.Argument(metavar="[BAG]", help="A recording (omit with --synthetic).",
                                               show_default=False)] = None,
    synthetic: Annotated[bool, typer.Option(
        "--synthetic", help="Use the built-in synthetic room (HDL-32-like rings) instead of a recording.")] = False,
    resolutions: Annotated[str, typer.Option(help="Comma-separated cell sizes in metres.")] = "0.1,0.2,0.4,0.8",
    scans: Annotated[int, typer.Option(min=1, help="Scans to time at each resolution.")] = 20,
    baseline: Annotated[str | None, typer.Option(
        help="Also time OctoMap on the same points: octomap (needs pyoctomap, the [bench] extra).",
        show_default=False)] = None,
    floor: Annotated[bool, typer.Option(
        "--floor/--no-floor", help="Also time the floor mode (traversal and one atomic per cell).")] = True,
    every: Annotated[int, typer.Option(min=1, help="Keep every N-th cloud of the recording.")] = 1,
    sensor_frame: Annotated[bool, typer.Option(
        "--sensor-frame", help="Identity poses (recordings without usable poses).")] = False,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
    out: Annotated[Path, typer.Option("--out", help="Folder for sweep.csv and sweep.png.")] = Path("ndtom_sweep"),
) -> None:
    """Time per scan against resolution (the paper's Fig. 5): NDT-OM, its floor mode and
    optionally OctoMap on the same scans, after a warm-up. Writes CSV, PNG and a table."""
    from . import sweep as sw

    with _user_errors(recording="`ndtom info BAG` shows what a recording holds"):
        try:
            res = [float(x) for x in resolutions.split(",") if x.strip()]
        except ValueError:
            raise ValueError(f"--resolutions must be numbers separated by commas, got {resolutions!r}") from None
        if not res or any(not (math.isfinite(r) and r > 0) for r in res):
            raise ValueError(f"--resolutions must be positive numbers of metres, got {resolutions!r}")
        if (bag is None) == (not synthetic):
            _fail("give either a recording BAG or --synthetic", "e.g. `ndtom sweep --synthetic --scans 10`")
        if baseline not in (None, "octomap"):
            _fail(f"unknown baseline {baseline!r}", "the supported baseline is `--baseline octomap`")
        if baseline == "octomap":
            _need_extra("pyoctomap", "the OctoMap baseline (--baseline octomap)", EXIT_USAGE)
        no_plot = _without_extra("matplotlib", "the sweep writes sweep.csv and the table but no sweep.png")
        out = out.expanduser()
        out.mkdir(parents=True, exist_ok=True)
        _check_writable(out / "sweep.csv", "CSV file")
        used = _init(arch)
        if synthetic or bag is None:  # one of the two, checked above
            from . import demo as demo_scene

            data = [(s.points, s.T_world_sensor) for s in demo_scene.make_scans(scans, per_ring=1800)]
            name = "synthetic room"
        else:
            from .io import open_recording

            with open_recording(bag) as rec:
                data = [(s.points, s.T_world_sensor)
                        for s in rec.scans(max_scans=scans, every=every, sensor_frame_only=sensor_frame)]
            name = bag.name
            if not data:
                _fail(f"no scans with poses in {bag}", "`ndtom info BAG` shows the pose sources")
        rows = sw.run_sweep(data, res, floor=floor, baseline=baseline,
                            progress=lambda msg: _err().print(Text(msg, style="cyan")))
        tags = {**sw.machine_tags(used), "data": name}  # the rows hold the number of scans
        csv_path = sw.write_csv(rows, out / "sweep.csv", tags)
        png_path = None if no_plot else sw.plot(rows, out / "sweep.png",
                                                f"{name}: {len(data)} scans, {used}, {tags['cores']} cores")
        t = _table(f"Sweep: {name}, {len(data)} scans of {sum(len(p) for p, _ in data) // len(data):,} points, "
                   f"{used}", "mapper", "res (m)", "median ms", "p95 ms", "Mpoints/s", "Mvisits/s",
                   "x NDT-OM", "Gaussians", "memory")
        for r in rows:
            t.add_row(r.mapper, f"{r.resolution:g}", f"{r.ms_median:.1f}", f"{r.ms_p95:.1f}",
                      f"{r.points_per_s / 1e6:.2f}", "-" if math.isnan(r.visits_per_s) else f"{r.visits_per_s / 1e6:.0f}",
                      "-" if math.isnan(r.ratio_to_ndtom) else f"{r.ratio_to_ndtom:.2f}",
                      "-" if r.gaussians is None else _count(r.gaussians), _mib(r.memory_bytes))
        _out().print(t)
        wrote = f"Wrote {csv_path} and {png_path}" if png_path else f"Wrote {csv_path} (no plot: matplotlib missing)"
        _out().print(wrote, soft_wrap=True, markup=False)


# ---------------------------------------------------------------------------- experiments
@app.command(short_help="Reproduce the paper's evaluation (Figs. 1-5).")
def experiments(
    source: Annotated[str, typer.Argument(
        metavar="SOURCE", help="A recording, a simworld .npz, or sim:dynamic / sim:static (the synthetic hall "
        "of simworld.py, see --simworld).", show_default=False)],
    resolution: Annotated[float, typer.Option("-r", "--resolution", help="Cell size in metres.",
                                              show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="Folder for CSVs, PNGs and summary.json.")] = Path(
        "ndtom_experiments"),
    every: Annotated[int, typer.Option(min=1, help="Keep every N-th cloud.")] = 1,
    max_scans: Annotated[int | None, typer.Option(min=1, help="Stop after this many scans.")] = None,
    sensor_frame: Annotated[bool, typer.Option("--sensor-frame", help="Identity poses.")] = False,
    coarsen: Annotated[int, typer.Option(min=2, help="Factor of the coarser map (Fig. 4d).")] = 3,
    sweep_res: Annotated[str | None, typer.Option(
        "--sweep", help="Also time these resolutions beside OctoMap (Fig. 5), e.g. 0.2,0.3,0.4.",
        show_default=False)] = None,
    sim_scans: Annotated[int, typer.Option(min=2, help="Scans of a sim: source.")] = 30,
    sim_stride: Annotated[int, typer.Option(min=1, help="Stride of a sim: source.")] = 10,
    simworld: Annotated[Path | None, typer.Option(
        help="simworld.py (or its folder) for sim: sources. Default: $NDTOM_SHARED/tools, else ../shared/tools.",
        show_default=False)] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Write PNG plots.")] = True,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
) -> None:
    """Reproduce the paper's evaluation (Figs. 1-5): Recursive NDT, NDT-OM and an online
    error-refinement baseline on the same scans, against the batch map."""
    from . import experiments as ex

    with _user_errors(recording="`ndtom info BAG` shows what a recording holds"):
        if not (math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"-r/--resolution must be a positive number of metres, got {resolution}")
        sweep_list = None
        if sweep_res:
            try:
                sweep_list = [float(x) for x in sweep_res.split(",") if x.strip()]
            except ValueError:
                raise ValueError(f"--sweep must be numbers separated by commas, got {sweep_res!r}") from None
        if source.startswith("sim:"):
            try:
                ex.find_simworld(simworld)
            except FileNotFoundError as exc:
                _fail(str(exc), "give it with --simworld PATH, or set NDTOM_SHARED")
        if plots and _without_extra("matplotlib", "no PNG plots (the CSVs and summary.json are written)"):
            plots = False
        if sweep_list:
            _without_extra("pyoctomap", "the --sweep times NDT-OM and its floor but not OctoMap")
        out = out.expanduser()
        out.mkdir(parents=True, exist_ok=True)
        _check_writable(out / "summary.json", "summary file")
        _init(arch)
        summary = ex.run_experiments(
            source, resolution, out, every=every, max_scans=max_scans, sensor_frame_only=sensor_frame,
            coarsen=coarsen, sweep=sweep_list, sim_scans=sim_scans, sim_stride=sim_stride, tools_dir=simworld,
            plots=plots,
            progress=lambda msg: _err().print(Text(msg, style="cyan")),
        )
        _out().print(ex.format_summary(summary), soft_wrap=True, markup=False, highlight=False)
        _out().print(f"Wrote {out / 'summary.json'} and the {'CSVs and figures' if plots else 'CSVs'} in {out}",
                     soft_wrap=True, markup=False)


# ---------------------------------------------------------------------------- view
@app.command(short_help="Look at a map in the browser, or write an HTML page.")
def view(
    map_file: Annotated[Path, typer.Argument(metavar="MAP", help="A map file written by `ndtom map`.",
                                             show_default=False)],
    host: Annotated[str, typer.Option(
        help="Address to serve on (default: this machine only; any other address prints a warning and a URL "
        "with an access token).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Port (the next free one if taken; the URL says which).")] = 8080,
    html: Annotated[Path | None, typer.Option(
        help="Write a standalone HTML snapshot of the scene and exit.", show_default=False)] = None,
    compare: Annotated[Path | None, typer.Option(
        help="A Recursive NDT map (ndtom map --no-occupancy) of the same data: highlights conflicting cells.",
        show_default=False)] = None,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
) -> None:
    """Look at a map in the browser: Gaussians as ellipsoids or splats, occupied and free
    cells, coarser levels, occupancy threshold. Prints the URL; Ctrl-C stops."""
    _need_extra("viser", "ndtom view")
    from .viewer.cli import view_command

    _init(arch)
    raise typer.Exit(view_command(map_file, host, port, html, compare=compare))


# ---------------------------------------------------------------------------- export
@app.command(short_help="Write a map as PLY, PCD, npz, CSV, OctoMap .bt or 2-D grid.")
def export(
    map_file: Annotated[Path, typer.Argument(metavar="MAP", help="A map file written by `ndtom map`.",
                                             show_default=False)],
    fmt: Annotated[Format | None, typer.Option(
        "-f", "--format", help="ply (Gaussian means coloured by height, with covariances), pcd (means with n and "
        "occupancy, for PCL tools), npz (all arrays), csv (one row per Gaussian), bt (OctoMap tree of occupied and "
        "free cells, for octovis and octomap_server), grid (2-D occupancy grid of a height band: PGM + YAML for "
        "ROS map_server). Default: from the -o suffix (.ply .pcd .npz .csv .bt .pgm .yaml; another suffix is "
        "refused), else ply.",
        show_default=False)] = None,
    output: Annotated[Path | None, typer.Option(
        "-o", "--output", help="File to write. Default: MAP with the format's suffix.", show_default=False)] = None,
    min_probability: Annotated[float, typer.Option(
        help="Occupied means occupancy probability above this (and above 0.5). ply, pcd, npz, csv: export the "
        "Gaussians above it (0: all Gaussians).")] = 0.5,
    z_min: Annotated[float | None, typer.Option(
        help="grid: bottom of the height band (m, map frame), with --z-max. Default: the band from 0.3 m (at "
        "least a cell) to 2 m above a floor plane fitted to the map's lowest Gaussians.", show_default=False)] = None,
    z_max: Annotated[float | None, typer.Option(
        help="grid: top of the height band (m, map frame), with --z-min.", show_default=False)] = None,
    arch: Annotated[Arch, typer.Option(help="Unused: export runs without Taichi (kept for older scripts).",
                                       hidden=True)] = Arch.auto,
) -> None:
    """Export a map: its Gaussians (ply, pcd, npz, csv), its cells as an OctoMap tree (bt),
    or a 2-D occupancy grid of a height band (grid: PGM + YAML as ROS map_server reads)."""
    from .export import DEFAULT_SUFFIX, export_file, format_for, grid_paths

    with _user_errors(map_file="give a map file written by `ndtom map` or `ndtom demo`"):
        try:
            fmt_name = format_for(output, fmt.value if fmt is not None else None)
        except ValueError as exc:
            _fail(str(exc), "name the format with --format, or use its suffix: e.g. -o map.bt, -o map.pgm")
        if not (0.0 <= min_probability < 1.0):
            raise ValueError(f"--min-probability must be in [0, 1), got {min_probability}")
        for name, z in (("--z-min", z_min), ("--z-max", z_max)):
            if z is not None and not math.isfinite(z):
                raise ValueError(f"{name} must be a finite height in metres, got {z}")
        if (z_min is not None or z_max is not None) and fmt_name != "grid":
            raise ValueError("--z-min/--z-max choose the height band of --format grid only")
        if (z_min is None) != (z_max is None):
            raise ValueError("give --z-min and --z-max together (or neither: 0.3 to 2 m above the floor)")
        if z_min is not None and z_max is not None and not z_min < z_max:
            raise ValueError(f"--z-min ({z_min}) must be below --z-max ({z_max})")
        if not map_file.exists():
            _fail(f"no map file at {map_file}", "give a map file written by `ndtom map` or `ndtom demo`")
        if map_file.is_dir():
            _fail(f"{map_file} is a folder, not a map file", "give a map file written by `ndtom map` or `ndtom demo`")
        out_path = _check_writable(output if output is not None else map_file.with_suffix(DEFAULT_SUFFIX[fmt_name]),
                                   f"{fmt_name} file")
        for t in grid_paths(out_path) if fmt_name == "grid" else (out_path,):
            if t.resolve() == map_file.resolve():
                _fail(f"the output {t} is the map file itself", "choose another path with -o")
        from .snapshot import MapSnapshot

        # a snapshot: numpy only, no map slot and no Taichi (--arch has nothing to choose)
        done = export_file(MapSnapshot.load(map_file), out_path, fmt_name, min_probability=min_probability,
                           z_min=z_min, z_max=z_max)  # fmt: skip
        size = sum(p.stat().st_size for p in done.paths)
        size_text = _mib(size) if size >= 2**20 else f"{size / 1024:.1f} KiB"
        _out().print(Text(f"Exported {done.summary} ({fmt_name}, {size_text})", style="green"), soft_wrap=True)
        for note in done.notes:
            _err().print(Text(f"note: {note}", style="dim"), soft_wrap=True)


def main() -> None:
    """Entry point of the ``ndtom`` command."""
    global _OWN_PROCESS
    _OWN_PROCESS = True  # signal handlers may stay until the process exits
    try:
        app(prog_name="ndtom")
    finally:
        # The work is saved; Python drops its handlers before Taichi's teardown, where a
        # late Ctrl-C or SIGTERM would otherwise kill the process instead of it exiting.
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, signal.SIG_IGN)


if __name__ == "__main__":  # pragma: no cover
    main()
