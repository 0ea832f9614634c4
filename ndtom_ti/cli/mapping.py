"""``ndtom map`` (a recording -> a map file) and ``ndtom demo`` (the built-in room -> a
map file, checked against its ground truth): options, the progress bar, the summary
table, and the save after a complete or stopped run. The loop is
:mod:`ndtom_ti.pipeline`'s."""

from __future__ import annotations

import math
import os
import time
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table
from rich.text import Text

from ..exitcodes import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK
from .common import (
    MAP_SUFFIX,
    Arch,
    MissModel,
    check_map_output,
    check_not_input,
    check_writable,
    console_err,
    console_out,
    fail,
    fmt_count,
    fmt_mib,
    frame_origin_text,
    init_taichi,
    make_table,
    need_extra,
    output_folder,
    own_process,
    partial_path,
    resolution_option,
    user_errors,
)
from .root import app
from .tiles import plan


# ---------------------------------------------------------------------------- map
def _memory_refusal(summary: Any, saved: str, map_options: bool = True) -> tuple[str, str]:
    """The error and hint of a scan the memory budget refused, in `ndtom map`'s options
    (``map_options`` False: in the demo's, which has no --memory-limit or --max-range)."""
    from .. import hostpool, runtime

    budget = runtime.pool_limit() / 2**30
    scan = summary.scans_used + 1
    error = (
        f"scan {scan} was refused: it could take Taichi's memory pool past its {budget:.2f} GiB budget"
        + (" (--memory-limit)" if map_options else "")
        + "; nothing of it was mapped"
    )
    ways = []
    note = runtime.pool_note()
    if not map_options:
        pass
    elif runtime.current_arch() == "cpu" and note is None:
        most = 0.8 * hostpool.physical_memory() / 2**30
        if most > budget * 1.1:
            ways.append(
                f"a larger --memory-limit (this machine has {hostpool.physical_memory() / 2**30:.0f} GiB; "
                f"e.g. --memory-limit {most:.0f})"
            )
    elif note is not None:
        ways.append(f"(--memory-limit cannot go past ~0.94 GiB here: {note})")
    ways.append(f"a coarser resolution (-r {2 * summary.resolution:g})")
    if map_options:
        ways.append("a smaller --max-range (long rays at a fine resolution touch the most cells)")
    if runtime.current_arch() == "cpu":
        ways.append("a CUDA device (--arch cuda)")
    more = " Or map a part: --max-scans N or --end T stops before it." if summary.scans_used and map_options else ""
    if len(ways) == 1:
        return error, f"{saved} To map scan {scan}, use {ways[0]}."
    return error, f"{saved} To map scan {scan}, use " + ", ".join(ways[:-1]) + f", or {ways[-1]}." + more


class CloudTime(str, Enum):
    header = "header"
    record = "record"


def default_output(bag: Path) -> Path:
    """The map path used without -o: the recording's name with .ndtom, in the current folder
    (a file inside a ROS2 bag folder, its metadata.yaml or storage file, names the folder)."""
    bag = bag.expanduser()
    in_ros2 = bag.name == "metadata.yaml" or bag.suffix in (".db3", ".mcap")
    if in_ros2 and bag.is_file() and (bag.parent / "metadata.yaml").is_file():
        bag = bag.resolve().parent
    name = bag.resolve().name if bag.name in ("", ".", "..") else bag.name
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
        self.compiled = 0  # kernels compiled (or loaded from Taichi's cache) during the run
        self._unlisten: Any = None

    def _compiling(self, name: str) -> None:
        # Taichi compiles each kernel at its first call: the first scans wait for it, so say
        # so (the bar is redrawn now: the compile holds the interpreter until it is done).
        self.compiled += 1
        if self.progress is not None:
            self.progress.update(
                self.task, description=f"compiling kernels, once per process ({self.compiled}: {name})", refresh=True
            )

    def __call__(self, summary: Any, report: Any) -> None:
        if report is None:  # the recording is fine: start Taichi and the bar
            self.arch_used = init_taichi(self.arch, self.memory_limit)
            from ..compiling import on_compile

            self._unlisten = on_compile(self._compiling)
            err = console_err()
            err.print(
                Text(
                    f"Mapping {summary.cloud_topic or summary.source} at {summary.resolution:g} m on "
                    f"{self.arch_used}; poses: {summary.pose_source or '-'}",
                    style="cyan",
                )
            )
            if self.show:
                self.progress = Progress(
                    TextColumn("[progress.description]{task.description}"),
                    BarColumn(),
                    MofNCompleteColumn(),
                    TextColumn("scans"),
                    TextColumn("{task.fields[rate]}"),
                    TimeElapsedColumn(),
                    console=Console(stderr=True),
                    transient=False,
                )
                self.task = self.progress.add_task("mapping", total=summary.scans_expected, rate="")
                self.progress.start()
            return
        if self.progress is not None:
            # the first scan compiles the kernels: no rate until a second one is in
            rate = f"{summary.points_per_second / 1e6:.2f} M points/s" if summary.scans_used > 1 else "compiling"
            total = summary.scans_expected
            done = summary.scans_used + summary.scans_resumed
            if total is not None and done > total:
                total = done
            self.progress.update(self.task, completed=done, total=total, rate=rate, description="mapping")

    def stop(self, summary: Any | None = None) -> None:
        if self._unlisten is not None:
            self._unlisten()
            self._unlisten = None
        if self.progress is not None:
            if summary is not None:
                done = summary.scans_used + summary.scans_resumed
                self.progress.update(
                    self.task, completed=done, total=done if summary.complete else self.progress.tasks[0].total
                )
            self.progress.stop()
            self.progress = None


# Why clouds were not mapped, in words (the pipeline's reasons are short keys).
_SKIP_WORDS = {"every": "left out by --every", "every_distance": "left out by --every-distance (sensor moved less)"}


def _skip_reason(reason: str) -> str:
    return _SKIP_WORDS.get(reason, reason)


def _summary_table(summary: Any, output: Path | None) -> Table:
    t = make_table("Mapping summary", "", "", header=False)
    t.add_row("source", escape(summary.source))
    if summary.cloud_topic:
        t.add_row("cloud topic", escape(f"{summary.cloud_topic} (frame {summary.frame_id})"))
    if summary.pose_source:
        t.add_row("poses", escape(summary.pose_source))
        t.add_row("map frame", escape(str(summary.fixed_frame)))
    if summary.frame_origin is not None:
        t.add_row("frame origin", escape(frame_origin_text(summary.frame_origin)))
    t.add_row("resolution", f"{summary.resolution:g} m" + ("" if summary.occupancy else " (no occupancy)"))
    resumed = (
        f" (and the first {fmt_count(summary.scans_resumed)}: the resumed checkpoint)" if summary.scans_resumed else ""
    )
    t.add_row("scans used", f"{fmt_count(summary.scans_used)} of {fmt_count(summary.clouds_seen)} clouds read{resumed}")
    skipped = ", ".join(f"{fmt_count(n)} {_skip_reason(reason)}" for reason, n in summary.skipped.items()) or "none"
    t.add_row("scans skipped", escape(skipped))
    t.add_row(
        "points",
        f"{fmt_count(summary.points_in)} in, {fmt_count(summary.points_used)} inserted"
        + (f", {fmt_count(summary.free_rays)} free rays" if summary.free_rays else ""),
    )
    d = summary.dropped
    t.add_row(
        "points dropped",
        f"{fmt_count(d['nonfinite'])} not finite, {fmt_count(d['range'])} out of range, "
        f"{fmt_count(d['outside_grid'])} outside the grid"
        + (f", {fmt_count(d['no_return'])} at (0, 0, 0) (no return)" if d.get("no_return") else ""),
    )
    t.add_row("Gaussians", fmt_count(summary.gaussians))
    t.add_row("known cells", fmt_count(summary.known_cells))
    t.add_row(
        "memory",
        f"{fmt_mib(summary.memory_bytes)} map; Taichi pool {fmt_mib(summary.pool_bytes)} of "
        f"{fmt_mib(summary.pool_budget_bytes)}",
    )
    if summary.scan_seconds:
        t.add_row(
            "time per scan",
            f"median {summary.ms_per_scan_median:.1f} ms, p95 {summary.ms_per_scan_p95:.1f} ms"
            f" (first scan {summary.ms_first_scan:.0f} ms, kernels compiled)",
        )
    later = " after the first scan" if summary.scans_used > 1 else ""
    t.add_row("total", f"{summary.wall_seconds:.2f} s ({summary.points_per_second / 1e6:.2f} M points/s{later})")
    if output is not None:
        t.add_row("map file", escape(str(output)))
    return t


def _rescue(m: Any, target: Path, compact: bool) -> Path | None:
    """Write the map somewhere else when its own path failed (a full disk, a dangling link):
    the current folder, then the temporary one. The path written, or None."""
    import tempfile

    name = f"{target.stem}.rescued-{os.getpid()}{MAP_SUFFIX}"
    for folder in dict.fromkeys((Path.cwd(), Path(tempfile.gettempdir()))):
        if folder.resolve() == target.parent.resolve():
            continue
        try:
            return m.save(folder / name, compact=compact)
        except (OSError, ValueError):
            continue
    return None


def _finish_mapping(
    m: Any,
    summary: Any,
    output: Path,
    bar: _Bar,
    extra_rows: list | None = None,
    signals: Any = None,
    compact: bool = False,
    keep_existing: bool = False,
    map_options: bool = True,
) -> int:
    """Print the summary, write the map (also after Ctrl-C, SIGTERM, a memory stop or a bad
    scan; ``compact``: its Gaussians rounded), return the exit code. ``signals``: the
    command's StopSignals; from here on a signal only waits for the map to be on disk.
    ``keep_existing``: ``output`` held a map before the run; a run that stopped early
    writes beside it (``partial_path``) and leaves that map as it was. ``map_options``
    False: the hints name only the options the demo has."""
    if signals is not None:
        signals.phase = "saving"
    bar.stop(summary)
    out, err = console_out(), console_err()
    wrote: Path | None = None
    target = partial_path(output) if keep_existing and not summary.complete else output
    if summary.scans_used or summary.scans_resumed:
        m.metadata.setdefault("options", {})["arch"] = bar.arch_used
        try:
            wrote = m.save(target, compact=compact)
        except OSError as exc:
            out.print(_summary_table(summary, None))
            rescued = _rescue(m, target, compact)  # the mapping is not lost with the save
            fail(
                f"cannot write the map to {target}: {exc}"
                + (f"; it was written to {rescued} instead" if rescued else "; nor could it be written elsewhere"),
                f"move {rescued} where it belongs" if rescued else "choose another path with -o",
                EXIT_FAILURE,
            )
    kept = f"; {output}, the map there before this run, is unchanged" if wrote and target != output else ""
    out.print(_summary_table(summary, wrote))
    for row in extra_rows or []:
        out.print(row)
    for note in summary.skip_notes:
        err.print(Text(f"note: {note}", style="dim"))
    if summary.stopped == "interrupted":
        name = signals.name if signals is not None and signals.count else "Ctrl-C"
        n = summary.scans_used + summary.scans_resumed
        msg = (
            f"Interrupted: saved the {n} scan{'s' if n != 1 else ''} mapped so far to {wrote} ({name}; the map is "
            f"marked incomplete){kept}"
            if wrote
            else f"Interrupted ({name}) before any scan was mapped; no map written"
        )
        err.print(Text(msg, style="bold yellow"))
        return signals.exit_code if signals is not None and signals.count else EXIT_INTERRUPTED
    if summary.stopped == "memory":
        saved = (
            f"Saved the {summary.scans_used + summary.scans_resumed} scans mapped before it to {wrote} "
            f"(marked incomplete){kept}."
            if wrote
            else "Nothing was mapped; no map written."
        )
        error, hint = _memory_refusal(summary, saved, map_options)
        err.print(Text.assemble(("Error: ", "bold red"), (error, "red")))
        err.print(Text.assemble(("Hint: ", "bold"), hint))
        return EXIT_FAILURE
    if summary.stopped == "error":
        err.print(Text.assemble(("Error: ", "bold red"), (summary.error or "a scan could not be mapped", "red")))
        saved = (
            f"Saved the {summary.scans_used + summary.scans_resumed} scans mapped before it to {wrote} "
            f"(marked incomplete){kept}."
            if wrote
            else "Nothing was mapped; no map written."
        )
        fix = "Check that scan's pose and cloud (`ndtom info BAG`), or end the run before it with --end or --max-scans."
        err.print(Text.assemble(("Hint: ", "bold"), f"{saved} {fix}"))
        return EXIT_FAILURE
    if not summary.scans_used and not summary.scans_resumed:
        why = ", ".join(f"{n} {_skip_reason(r)}" for r, n in summary.skipped.items()) or "the selection is empty"
        fail(
            f"no scans were mapped ({summary.clouds_seen} clouds: {why}); no map written",
            "check --start/--end/--every and the pose source (`ndtom info BAG`)",
        )
    assert wrote is not None  # scans were mapped, so the map was written (or fail above)
    out.print(Text(f"Map written to {wrote} ({fmt_mib(wrote.stat().st_size)})", style="green"), soft_wrap=True)
    return EXIT_OK


@app.command("map", short_help="Map a recording (ROS1 bag or ROS2 folder) into a map file.")
def map_(
    bag: Annotated[
        Path,
        typer.Argument(
            metavar="BAG",
            help="A ROS1 .bag file, a folder of them (one recording, split), or a ROS2 bag folder (sqlite3 or mcap).",
            show_default=False,
        ),
    ],
    resolution: Annotated[float, typer.Option("-r", "--resolution", help="Cell size in metres.", show_default=False)],
    output: Annotated[
        Path | None,
        typer.Option(
            "-o",
            "--output",
            help="Map file to write (atomically). Default: the recording's name with .ndtom, "
            "in the current folder (site.bag -> ./site.ndtom).",
            show_default=False,
        ),
    ] = None,
    compact: Annotated[
        bool,
        typer.Option(
            "--compact",
            help="Write the Gaussians rounded (means to res/131070, scatter to float32): about half the file "
            "where Gaussians are dense (indoors). Not lossless; the default is.",
        ),
    ] = False,
    cloud_topic: Annotated[
        str | None,
        typer.Option(
            help="The topic to map (PointCloud2, Livox CustomMsg, depth image or LaserScan); needed only "
            "when the recording has several. Several sensors into one map: /front,/rear."
        ),
    ] = None,
    fixed_frame: Annotated[
        str | None, typer.Option(help="Frame of the map; default: the root of the cloud frame's TF tree.")
    ] = None,
    poses: Annotated[
        Path | None,
        typer.Option(help="Pose file (TUM: t tx ty tz qx qy qz qw, or KITTI 3x4 rows) giving T_world_sensor."),
    ] = None,
    pose_topic: Annotated[
        str | None, typer.Option(help="Pose topic (Odometry, PoseStamped, ...) to use instead of TF.")
    ] = None,
    sensor_frame: Annotated[
        bool, typer.Option("--sensor-frame", help="No poses: map every scan in the sensor frame (identity poses).")
    ] = False,
    ray_origin_frame: Annotated[
        str | None,
        typer.Option(
            help="Rays start at this TF frame's origin instead of the cloud frame's: clouds published in a "
            "vehicle or world frame (registered clouds); poses from TF, or from --pose-topic and TF from its frame.",
            show_default=False,
        ),
    ] = None,
    pose_child_frame: Annotated[
        str | None,
        typer.Option(
            help="With --pose-topic (or a pose topic found): the frame its poses are of when its messages name "
            "none (PoseStamped, PoseWithCovarianceStamped). Default: the frame tf_static mounts the cloud frame on "
            "(base_link), else the cloud frame.",
            show_default=False,
        ),
    ] = None,
    static_transform: Annotated[
        list[str] | None,
        typer.Option(
            metavar="'X Y Z QX QY QZ QW PARENT CHILD'",
            help="A mount the recording lacks (its /tf_static not recorded), as static_transform_publisher takes "
            "it (or X Y Z YAW PITCH ROLL PARENT CHILD); repeat for more.",
            show_default=False,
        ),
    ] = None,
    tf_topic: Annotated[
        str | None,
        typer.Option(
            help="The TF topic (or its namespace) of the robot carrying the sensor, where several robots' "
            "namespaced TF topics (/robot1/tf, /robot2/tf) give the same frames; its tf_static comes with it. "
            "Default: those of the cloud topic's namespace.",
            show_default=False,
        ),
    ] = None,
    cloud_time: Annotated[
        CloudTime,
        typer.Option(
            help="A cloud's time: its header stamp, or the bag's record time (clouds stamped on the sensor's own "
            "clock, which the poses are not on).",
        ),
    ] = CloudTime.header,
    every: Annotated[int, typer.Option(min=1, help="Keep every N-th cloud.")] = 1,
    every_distance: Annotated[
        float | None,
        typer.Option(min=0.0, help="Keep a cloud once the sensor moved this far (m) from the last kept one."),
    ] = None,
    start: Annotated[float | None, typer.Option(help="Skip clouds before this time (s from the bag start).")] = None,
    end: Annotated[float | None, typer.Option(help="Skip clouds after this time (s from the bag start).")] = None,
    max_scans: Annotated[int | None, typer.Option(min=1, help="Stop after this many scans.")] = None,
    max_range: Annotated[float | None, typer.Option(help="Drop points farther than this (m).")] = None,
    min_range: Annotated[float | None, typer.Option(help="Drop points closer than this (m).")] = None,
    occupancy: Annotated[
        bool,
        typer.Option(
            "--occupancy/--no-occupancy", help="Ray-trace free space (NDT-OM); --no-occupancy: Gaussians only."
        ),
    ] = True,
    miss_model: Annotated[
        MissModel | None,
        typer.Option(
            "--miss-model",
            help="How rays lower cells holding a Gaussian: ndt (by how squarely they pass it, "
            "IJRR 2013) or paper (a constant per ray, eq. 12). Default: the config's, else ndt.",
        ),
    ] = None,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
    memory_limit: Annotated[
        float | None,
        typer.Option(
            "--memory-limit",
            metavar="GIB",
            help="Memory budget of the map's sparse cells (GiB of Taichi's pool). "
            "Default: half of the machine's memory on the CPU, 90% of the device pool on CUDA.",
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(
            help="JSON or TOML file of MapConfig options (p_occupied, p_empty, logodds_min, logodds_max, "
            "min_points, min_range, max_range, max_range_mode, n_max, miss_model, sigma_s, eta); -r, --min-range, "
            "--max-range, --miss-model win."
        ),
    ] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
    view: Annotated[
        bool,
        typer.Option(
            "--view",
            help="Map live in the browser viewer, at the recording's own rate, starting when a browser "
            "connects; the map is saved at the end and on Ctrl-C or SIGTERM.",
        ),
    ] = False,
    host: Annotated[str, typer.Option(help="Viewer host (with --view).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Viewer port (with --view).")] = 8080,
    rate: Annotated[
        str,
        typer.Option(
            help="With --view: playback speed, times the recording's rate (1: as recorded, 2: twice as fast, "
            "max: as fast as mapping goes)."
        ),
    ] = "1",
    no_wait: Annotated[
        bool, typer.Option("--no-wait", help="With --view: start mapping at once, not when the first browser connects.")
    ] = False,
    workers: Annotated[
        int | None,
        typer.Option(
            metavar="N",
            help="Map with N worker processes on Ray (extra [cluster]), each updating the cells of its own tiles: "
            "the same map file, cell for cell.",
            show_default=False,
        ),
    ] = None,
    tile_size: Annotated[
        float | None,
        typer.Option(
            "--tile-size",
            metavar="METRES",
            help="With --workers: edge of the cubic tiles shared among the workers (default 16).",
            show_default=False,
        ),
    ] = None,
    cluster: Annotated[
        str | None,
        typer.Option(
            metavar="ADDRESS",
            help="With --workers: join the running Ray cluster at ADDRESS (host:port) instead of starting a local one.",
            show_default=False,
        ),
    ] = None,
    tiled: Annotated[
        Path | None,
        typer.Option(
            metavar="DIR",
            help="With --workers: write the checkpoints to DIR and keep it, a tiled map (`ndtom merge`, info, export "
            "and view read it). Default: the map file's name with .tiles added, beside it (site.ndtom.tiles), removed "
            "after a complete run.",
            show_default=False,
        ),
    ] = None,
    checkpoint_every: Annotated[
        int | None,
        typer.Option(
            metavar="K",
            help="With --workers: checkpoint every K scans (default 100; 0: only at the end); a lost worker "
            "restarts the job from the last one.",
            show_default=False,
        ),
    ] = None,
    resume: Annotated[
        bool,
        typer.Option(
            "--resume",
            help="With --workers: carry on from the checkpoint of a stopped run (--tiled DIR, else site.ndtom.tiles "
            "beside -o site.ndtom), "
            "skipping the scans it holds; give the stopped run's options.",
        ),
    ] = False,
    worker_threads: Annotated[
        int | None,
        typer.Option(
            metavar="N",
            help="With --workers: CPU threads of each worker. Default: this machine's CPUs shared among the workers "
            "(with --cluster: Taichi's default).",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Map a recording into an NDT Occupancy Map file.

    Prints a progress bar, then a summary (scans used and skipped and why, points,
    Gaussians, memory, time per scan). Ctrl-C (or SIGTERM) stops after the current scan
    and saves what was mapped (exit 130, or 143).
    """
    from .. import pipeline
    from ..io.selection import ScanSelection
    from ..signals import stop_signals

    code = EXIT_OK
    with user_errors():
        resolution = resolution_option(resolution)
        given = [
            n
            for n, v in (
                ("--poses", poses),
                ("--pose-topic", pose_topic),
                ("--sensor-frame", sensor_frame),
            )
            if v
        ]
        if len(given) > 1:
            raise ValueError(f"give one pose source, not {' and '.join(given)}")
        if ray_origin_frame and (poses or sensor_frame):
            raise ValueError(f"--ray-origin-frame goes with poses from TF or --pose-topic, not with {given[0]}")
        if pose_child_frame and (poses or sensor_frame):
            raise ValueError(f"--pose-child-frame goes with poses from a pose topic, not with {given[0]}")
        if every > 1 and every_distance is not None:
            raise ValueError("give --every or --every-distance, not both")
        for opt, v in (("--start", start), ("--end", end)):
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{opt} must be a number of seconds from the recording's start, got {v}")
        if start is not None and end is not None and end < start:
            raise ValueError(f"--end ({end}) is before --start ({start})")
        if memory_limit is not None:
            from ..hostpool import physical_memory

            if not (math.isfinite(memory_limit) and memory_limit > 0):
                raise ValueError(f"--memory-limit must be a positive number of GiB, got {memory_limit}")
            if memory_limit * 2**30 > physical_memory():
                raise ValueError(
                    f"--memory-limit {memory_limit:g} GiB is more than this machine's "
                    f"{physical_memory() / 2**30:.1f} GiB of memory"
                )
        cfg = pipeline.load_config_file(config) if config is not None else None
        mapcfg = pipeline.config_with_ranges(
            cfg, min_range=min_range, max_range=max_range, miss_model=miss_model.value if miss_model else None
        )
        out_path = output if output is not None else default_output(bag)
        inputs = {"recording": bag, "pose file": poses, "config file": config}
        check_not_input(out_path, inputs)
        out_path = check_writable(out_path, "map file")
        check_map_output(out_path)
        # a map there already: a run that stops early writes beside it, keeping that one
        keep_existing = out_path.is_file() and out_path.stat().st_size > 0
        if keep_existing:
            check_not_input(partial_path(out_path), inputs)
            check_writable(partial_path(out_path), "map file")
            check_map_output(partial_path(out_path))
        tiles = plan(
            resolution=resolution,
            workers=workers,
            tile_size=tile_size,
            cluster=cluster,
            tiled=tiled,
            checkpoint_every=checkpoint_every,
            resume=resume,
            worker_threads=worker_threads,
            memory_limit=memory_limit,
            output=out_path,
            view=view,
        )
        selection = ScanSelection(
            cloud_topic=cloud_topic,
            fixed_frame=fixed_frame,
            pose_topic=pose_topic,
            poses_file=poses,
            sensor_frame_only=sensor_frame,
            ray_origin_frame=ray_origin_frame,
            pose_child_frame=pose_child_frame,
            cloud_time=cloud_time.value,
            static_transforms=tuple(static_transform or ()),
            tf_topic=tf_topic,
            every=every,
            every_distance=every_distance,
            t_start=start,
            t_end=end,
            max_scans=max_scans,
        )
        if view:
            need_extra("viser", "the live viewer (--view)")
            from ..viewer.cli import live_recording_command, parse_rate

            speed = parse_rate(rate)
            init_taichi(arch, memory_limit)
            bar = _Bar(arch, progress, memory_limit)
            try:
                code = live_recording_command(
                    bag,
                    resolution,
                    selection=selection,
                    occupancy=occupancy,
                    config=mapcfg,
                    host=host,
                    port=port,
                    speed=speed,
                    wait_for_browser=not no_wait,
                    metadata={"command": "ndtom map --view", "config_file": str(config.resolve()) if config else None},
                    progress=bar,
                    finish=lambda m, summary, signals=None: _finish_mapping(
                        m, summary, out_path, bar, signals=signals, compact=compact, keep_existing=keep_existing
                    ),
                )
            finally:
                bar.stop()
            raise typer.Exit(code)

        bar = _Bar(arch, progress, memory_limit)
        metadata: dict[str, Any] = {"command": "ndtom map", "config_file": str(config.resolve()) if config else None}
        if tiles is not None:
            tiles.set_job(
                {
                    "recording": str(Path(bag).resolve()),
                    # where a run stops (--max-scans, --end) may change when it is resumed
                    "selection": {k: v for k, v in selection.options().items() if k not in ("max_scans", "end")},
                    "occupancy": occupancy,
                    "config": mapcfg.to_dict(),
                }
            )
            metadata["workers"] = {"workers": tiles.workers, "tile_size": tiles.tile_size, "engine": "ray"}
            console_err().print(Text(tiles.describe(), style="cyan"))
        # Ctrl-C and SIGTERM: finish the scan in hand, save, then exit
        with stop_signals(restore=not own_process()) as sig:
            try:
                m, summary = pipeline.map_recording(
                    bag,
                    resolution,
                    selection,
                    occupancy=occupancy,
                    config=mapcfg,
                    metadata=metadata,
                    progress=bar,
                    make_map=tiles.make_map() if tiles is not None else None,
                )
            except BaseException:
                bar.stop()
                raise
            try:
                if tiles is not None:
                    sig.phase = "saving"  # from here on a signal waits for the checkpoint and the map
                    bar.stop(summary)
                    tiles.finish(m, summary, "ndtom map")
                code = _finish_mapping(
                    m, summary, out_path, bar, signals=sig, compact=compact, keep_existing=keep_existing
                )
            finally:
                m.close()  # its slot (or its workers) back now: the map is on disk
            if tiles is not None and code == EXIT_OK:
                tiles.clean(summary)
    raise typer.Exit(code)


# ---------------------------------------------------------------------------- demo
@app.command(short_help="Map a built-in synthetic room; check it against the truth.")
def demo(
    out: Annotated[Path, typer.Option("--out", help="Folder for the map (created if missing).")] = Path("ndtom_demo"),
    resolution: Annotated[float, typer.Option("-r", "--resolution", help="Cell size in metres.")] = 0.2,
    scans: Annotated[int, typer.Option(min=2, max=1000, help="Number of scans.")] = 20,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
    view: Annotated[
        bool,
        typer.Option(
            "--view",
            help="Map the room live in the browser viewer (starting when a browser connects); writes the map too.",
        ),
    ] = False,
    port: Annotated[int, typer.Option(help="Viewer port (with --view).")] = 8080,
    rate: Annotated[
        str,
        typer.Option(
            help="With --view: playback speed, times the scans' rate (1: 10 scans/s as recorded, max: as fast as "
            "mapping goes)."
        ),
    ] = "1",
    no_wait: Annotated[
        bool, typer.Option("--no-wait", help="With --view: start mapping at once, not when the first browser connects.")
    ] = False,
) -> None:
    """Map a built-in synthetic room (walls, floor, boxes, one box that is taken away
    halfway) and check the map against the exact ground truth. Writes OUT/demo.ndtom."""
    from .. import demo as demo_scene
    from ..pipeline import map_scans
    from ..signals import stop_signals

    code = EXIT_OK
    with user_errors():
        resolution = resolution_option(resolution)
        if view:
            need_extra("viser", "the live viewer (--view)")
        out = output_folder(out, "the demo's output")
        out_path = check_writable(out / ("demo" + MAP_SUFFIX), "map file")
        check_map_output(out_path, "--out")
        scene = demo_scene.Scene()
        t0 = time.perf_counter()
        data = demo_scene.make_scans(scans, scene=scene)
        console_err().print(
            Text(
                f"Demo scene: a 12 x 8 m room, {len(scene.boxes)} boxes (one taken away after scan "
                f"{scene.vanishing[0].present_until}), {len(data)} lidar scans of about "
                f"{sum(len(s.points) for s in data) // len(data):,} points, made in "
                f"{time.perf_counter() - t0:.1f} s",
                style="cyan",
            )
        )
        if view:
            from ..viewer.cli import live_demo_command, parse_rate

            speed = parse_rate(rate)
            init_taichi(arch)
            bar = _Bar(arch, progress)
            try:
                code = live_demo_command(
                    "127.0.0.1",
                    port,
                    resolution=resolution,
                    n_scans=scans,
                    scans=data,
                    speed=speed,
                    wait_for_browser=not no_wait,
                    progress=bar,
                    metadata={
                        "command": "ndtom demo --view",
                        "demo": {"scans": scans, "scene": "room 12x8x3 m, 5 boxes"},
                    },
                    finish=lambda m, summary, signals=None: _finish_mapping(
                        m, summary, out_path, bar, signals=signals, map_options=False
                    ),
                )
            finally:
                bar.stop()
            raise typer.Exit(code)
        bar = _Bar(arch, progress)
        with stop_signals(restore=not own_process()) as sig:  # as in `ndtom map`
            try:
                m, summary = map_scans(
                    data,
                    resolution,
                    source="ndtom demo (synthetic room)",
                    scans_expected=len(data),
                    pose_source="exact (synthetic)",
                    fixed_frame="world",
                    metadata={"command": "ndtom demo", "demo": {"scans": scans, "scene": "room 12x8x3 m, 5 boxes"}},
                    progress=bar,
                )
            except BaseException:
                bar.stop()
                raise
            rows = []
            if summary.scans_used:  # nothing to check a map without scans against
                check = demo_scene.ground_truth_check(m.gaussians(), resolution, scene)
                m.metadata["ground_truth_check"] = check
                rows.append(_truth_table(check, resolution))
            code = _finish_mapping(m, summary, out_path, bar, rows, signals=sig, map_options=False)
            m.close()  # its slot back now: the map is on disk
        if code == EXIT_OK:
            console_out().print(_demo_next(out_path), soft_wrap=True, markup=False)
    raise typer.Exit(code)


def _truth_table(check: dict, resolution: float) -> Any:
    """The demo map's ground-truth check as a table."""
    gt = make_table("Against the ground truth", "", "", header=False)
    if check["gaussians"]:
        on = f"{check['on_surface'] * 100:.1f}% (mean within {resolution / 4:g} m)"
        gt.add_row("Gaussians on a true surface", on)
        gt.add_row("median distance to surface", f"{check['median_distance'] * 1000:.1f} mm")
    else:
        gt.add_row("Gaussians on a true surface", "none: the map holds no Gaussian")
    gt.add_row("left where the box was taken away", str(check["left_in_vanished"]))
    return gt


def _demo_next(out_path: Path) -> str:
    """What to do with the demo's map: see it in the browser, or export it."""
    from ..extras import available, install_hint

    view = f"ndtom view {out_path}  (the map in the browser)"
    if not available("viser"):
        view = f"{view}, after: {install_hint('viewer')}"
    return f"Next: {view}\n      ndtom export {out_path} -o demo.ply  (or .bt .pcd .pgm)"
