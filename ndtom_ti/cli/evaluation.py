"""``ndtom sweep`` (time per scan against resolution beside OctoMap, the paper's Fig. 5)
and ``ndtom experiments`` (the paper's Figs. 1-5): options and tables; the work is
:mod:`ndtom_ti.evaluation`'s."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer
from rich.text import Text

from ..exitcodes import EXIT_FAILURE
from .common import (
    Arch,
    check_writable,
    console_err,
    console_out,
    fail,
    fmt_count,
    fmt_mib,
    init_taichi,
    make_table,
    need_extra,
    output_folder,
    own_process,
    resolution_list,
    resolution_option,
    user_errors,
    without_extra,
)
from .root import app


# ---------------------------------------------------------------------------- shared
def _own_words(text: str, command: str) -> str:
    """A recording's error with its advice on poses in this command's options (it names
    `ndtom map`'s, which these commands do not have)."""
    from ..io.recording import POSE_ADVICE

    return text.replace(
        POSE_ADVICE,
        f"`ndtom {command}` takes the poses a recording holds (its TF tree or a single pose topic), or "
        "identity poses with --sensor-frame; `ndtom map` also takes --poses FILE and --pose-topic.",
    )


@contextlib.contextmanager
def _recording_errors(command: str) -> Iterator[None]:
    from ..io import RecordingError

    try:
        yield
    except RecordingError as exc:
        fail(_own_words(str(exc), command), "`ndtom info BAG` shows what a recording holds")


def _resolutions(text: str, option: str) -> list[float]:
    """``option``'s comma-separated resolutions: an empty entry is refused, a repeated one
    timed once (with a note)."""
    if any(not part.strip() for part in text.split(",")):
        fail(f"{option} {text!r} has an empty entry", f"give the cell sizes separated by commas, e.g. {option} 0.2,0.4")
    values = resolution_list(text, option)
    unique = list(dict.fromkeys(values))
    if len(unique) < len(values):
        twice = sorted({v for v in values if values.count(v) > 1})
        console_err().print(
            Text(f"note: {option} lists {', '.join(f'{v:g}' for v in twice)} m more than once: timed once", style="dim")
        )
    return unique


def _out_folder(out: str, what: str) -> Path:
    if not out.strip():
        fail("--out is empty", f"give a folder for {what}, e.g. --out results")
    return output_folder(Path(out), what)


def _import_extra(module: str) -> str | None:
    """Why ``module``, found installed, cannot be imported (None: it imports, or is not installed)."""
    from ..extras import available, import_error

    return import_error(module) if available(module) else None


def _need_import(module: str, purpose: str) -> None:
    """``need_extra``, and the module must import too: refused before any work."""
    from ..extras import broken_message, reinstall_hint

    need_extra(module, purpose)
    error = _import_extra(module)
    if error is not None:
        fail(broken_message(module, purpose, error), reinstall_hint(module), EXIT_FAILURE)


def _skip_broken(module: str, skipped: str) -> str | None:
    """Why ``module`` is skipped (after a note): it is missing (``without_extra``) or
    installed but cannot be imported; None when it imports."""
    from ..extras import reinstall_hint

    if without_extra(module, skipped):
        return f"{module} missing"
    error = _import_extra(module)
    if error is None:
        return None
    console_err().print(
        Text(
            f"note: {module} is installed but cannot be imported ({error}): {skipped}; {reinstall_hint(module)}",
            style="yellow",
        ),
        soft_wrap=True,
    )
    return f"{module} cannot be imported"


def _memory_text(exc: BaseException) -> str:
    """A MapMemoryError's account without its advice, which names the API's options."""
    text = str(exc)
    return text.split(" Use a coarser")[0].rstrip(". ")


def _too_fine(exc: Exception, option: str) -> None:
    from ..evaluation.sweep import ResolutionTooFineError

    if isinstance(exc, ResolutionTooFineError):
        fail(
            f"{option}: {exc}",
            f"drop {', '.join(f'{r:g}' for r in exc.resolutions)} from {option}, or give {exc.finest:g} m or coarser",
        )


# ---------------------------------------------------------------------------- sweep
@app.command(short_help="Time per scan against resolution, beside OctoMap (Fig. 5).")
def sweep(
    bag: Annotated[
        Path | None, typer.Argument(metavar="[BAG]", help="A recording (omit with --synthetic).", show_default=False)
    ] = None,
    synthetic: Annotated[
        bool,
        typer.Option("--synthetic", help="Use the built-in synthetic room (HDL-32-like rings) instead of a recording."),
    ] = False,
    resolutions: Annotated[str, typer.Option(help="Comma-separated cell sizes in metres.")] = "0.1,0.2,0.4,0.8",
    scans: Annotated[int, typer.Option(min=1, help="Scans to time at each resolution.")] = 20,
    baseline: Annotated[
        str | None,
        typer.Option(
            help="Also time OctoMap on the same points: octomap (needs pyoctomap, the [bench] extra).",
            show_default=False,
        ),
    ] = None,
    floor: Annotated[
        bool, typer.Option("--floor/--no-floor", help="Also time the floor mode (traversal and one atomic per cell).")
    ] = True,
    every: Annotated[int, typer.Option(min=1, help="Keep every N-th cloud of the recording.")] = 1,
    sensor_frame: Annotated[
        bool, typer.Option("--sensor-frame", help="Identity poses (recordings without usable poses).")
    ] = False,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
    out: Annotated[str, typer.Option("--out", help="Folder for sweep.csv and sweep.png.")] = "ndtom_sweep",
) -> None:
    """Time per scan against resolution (the paper's Fig. 5): NDT-OM, its floor mode and
    optionally OctoMap on the same scans, after a warm-up. Writes CSV, PNG and a table.
    Ctrl-C, SIGTERM or a resolution that does not fit in memory stops the sweep; the rows
    finished are written, marked partial (column complete = false)."""
    from ..evaluation import sweep as sw
    from ..evaluation.stops import catch_stops, writing
    from ..runtime import MapMemoryError

    with (
        user_errors(recording="`ndtom info BAG` shows what a recording holds"),
        catch_stops(restore=not own_process()) as stops,
    ):
        res = _resolutions(resolutions, "--resolutions")
        if (bag is None) == (not synthetic):
            fail("give either a recording BAG or --synthetic", "e.g. `ndtom sweep --synthetic --scans 10`")
        if baseline not in (None, "octomap"):
            fail(f"unknown baseline {baseline!r}", "the supported baseline is `--baseline octomap`")
        if baseline == "octomap":
            _need_import("pyoctomap", "the OctoMap baseline (--baseline octomap)")
        no_plot = _skip_broken("matplotlib", "the sweep writes sweep.csv and the table but no sweep.png")
        folder = _out_folder(out, "sweep.csv and sweep.png")
        check_writable(folder / "sweep.csv", "CSV file", option="--out")
        used = init_taichi(arch)
        if synthetic or bag is None:  # one of the two, checked above
            from .. import demo as demo_scene

            data = demo_scene.make_scans(scans, per_ring=1800)
            name = "synthetic room"
        else:
            from ..io import open_recording

            with _recording_errors("sweep"), open_recording(bag) as rec:
                data = list(rec.scans(max_scans=scans, every=every, sensor_frame_only=sensor_frame))
            name = bag.name
            if not data:
                fail(f"no scans with poses in {bag}", "`ndtom info BAG` shows the pose sources")
        try:
            sw.check_grid(data, res)
        except ValueError as exc:
            _too_fine(exc, "--resolutions")
            raise
        rows: list = []
        stopped: BaseException | None = None
        try:
            sw.run_sweep(
                data,
                res,
                floor=floor,
                baseline=baseline,
                progress=lambda msg: console_err().print(Text(msg, style="cyan")),
                on_row=rows.append,
            )
        except (KeyboardInterrupt, MapMemoryError) as exc:
            stopped = exc
        stops.phase = "writing"  # from here on a signal waits for the files
        mappers = 1 + floor + (baseline == "octomap")
        timed = [r for r in res if sum(row.resolution == r for row in rows) == mappers]
        in_hand = next((r for r in res if r not in timed), None)
        signal_stop = isinstance(stopped, KeyboardInterrupt)
        why = None
        if stopped is not None:
            why = f"{stops.name if signal_stop else 'memory'} at {in_hand:g} m"
        if stopped is not None and not rows:
            if signal_stop:
                fail(
                    f"interrupted ({stops.name}) before any resolution was timed; nothing was written",
                    None,
                    stops.exit_code,
                )
            fail(
                f"at {in_hand:g} m the map does not fit in memory: {_memory_text(stopped)}; nothing was written",
                _sweep_memory_hint(in_hand),
                EXIT_FAILURE,
            )
        tags = {
            **sw.machine_tags(used),
            "data": name,  # the rows hold the number of scans
            "complete": "true" if stopped is None else "false",
            "stopped": why or "",
        }
        with writing():
            csv_path = sw.write_csv(rows, folder / "sweep.csv", tags)
            title = f"{name}: {len(data)} scans, {used}, {tags['cores']} cores" + (" (partial)" if why else "")
            png_path = None if no_plot else sw.plot(rows, folder / "sweep.png", title)
        t = make_table(
            f"Sweep: {name}, {len(data)} scans of {sum(len(s.points) for s in data) // len(data):,} points, {used}"
            + (" (partial)" if why else ""),
            "mapper",
            "res (m)",
            "median ms",
            "p95 ms",
            "Mpoints/s",
            "Mvisits/s",
            "x NDT-OM",
            "Gaussians",
            "memory",
        )
        for r in rows:
            t.add_row(
                r.mapper,
                f"{r.resolution:g}",
                f"{r.ms_median:.1f}",
                f"{r.ms_p95:.1f}",
                f"{r.points_per_s / 1e6:.2f}",
                "-" if math.isnan(r.visits_per_s) else f"{r.visits_per_s / 1e6:.0f}",
                "-" if math.isnan(r.ratio_to_ndtom) else f"{r.ratio_to_ndtom:.2f}",
                "-" if r.gaussians is None else fmt_count(r.gaussians),
                fmt_mib(r.memory_bytes),
            )
        console_out().print(t)
        wrote = f"Wrote {csv_path} and {png_path}" if png_path else f"Wrote {csv_path} (no plot: {no_plot})"
        console_out().print(wrote, soft_wrap=True, markup=False)
        if stopped is None:
            return
        rest = [r for r in res if r not in timed]
        partial = (
            f"Wrote the {len(rows)} row{'s' if len(rows) != 1 else ''} finished to {csv_path}, marked partial "
            f"(complete = false, stopped = {why}); not timed in full: {', '.join(f'{r:g}' for r in rest)} m"
        )
        if signal_stop:
            console_err().print(Text(f"Interrupted ({stops.name}). {partial}", style="bold yellow"), soft_wrap=True)
            raise typer.Exit(stops.exit_code)
        fail(
            f"at {in_hand:g} m the map does not fit in memory: {_memory_text(stopped)}. {partial}",
            _sweep_memory_hint(in_hand),
            EXIT_FAILURE,
        )


def _sweep_memory_hint(res: float | None) -> str:
    drop = f"drop {res:g} from --resolutions or use coarser ones" if res is not None else "use coarser --resolutions"
    return f"{drop}, time fewer scans (--scans, --every), or use a CUDA device (--arch cuda)"


# ---------------------------------------------------------------------------- experiments
@app.command(short_help="Reproduce the paper's evaluation (Figs. 1-5).")
def experiments(
    source: Annotated[
        str,
        typer.Argument(
            metavar="SOURCE",
            help="A recording, a simworld .npz, or sim:dynamic / sim:static (the synthetic hall "
            "of simworld.py, see --simworld).",
            show_default=False,
        ),
    ],
    resolution: Annotated[float, typer.Option("-r", "--resolution", help="Cell size in metres.", show_default=False)],
    out: Annotated[str, typer.Option("--out", help="Folder for CSVs, PNGs and summary.json.")] = "ndtom_experiments",
    every: Annotated[int, typer.Option(min=1, help="Keep every N-th cloud.")] = 1,
    max_scans: Annotated[int | None, typer.Option(min=1, help="Stop after this many scans.")] = None,
    sensor_frame: Annotated[bool, typer.Option("--sensor-frame", help="Identity poses.")] = False,
    coarsen: Annotated[int, typer.Option(min=2, help="Factor of the coarser map (Fig. 4d).")] = 3,
    sweep_res: Annotated[
        str | None,
        typer.Option(
            "--sweep", help="Also time these resolutions beside OctoMap (Fig. 5), e.g. 0.2,0.3,0.4.", show_default=False
        ),
    ] = None,
    sim_scans: Annotated[int, typer.Option(min=2, help="Scans of a sim: source.")] = 30,
    sim_stride: Annotated[int, typer.Option(min=1, help="Stride of a sim: source.")] = 10,
    simworld: Annotated[
        Path | None,
        typer.Option(
            help="simworld.py (or its folder): the generator that sim: sources need (not part of ndtom_ti).",
            show_default=False,
        ),
    ] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Write PNG plots.")] = True,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
) -> None:
    """Reproduce the paper's evaluation (Figs. 1-5): Recursive NDT, NDT-OM and an online
    error-refinement baseline on the same scans, against the batch map."""
    from ..evaluation import experiments as ex
    from ..evaluation.report import format_summary
    from ..evaluation.sources import find_simworld
    from ..evaluation.stops import catch_stops
    from ..runtime import MapMemoryError

    with (
        user_errors(recording="`ndtom info BAG` shows what a recording holds"),
        catch_stops(restore=not own_process()) as stops,
    ):
        resolution = resolution_option(resolution)
        sweep_list = _resolutions(sweep_res, "--sweep") if sweep_res is not None else None
        if source.startswith("sim:"):
            try:
                find_simworld(simworld)
            except FileNotFoundError as exc:
                fail(str(exc), "give it with --simworld PATH")
        if plots and _skip_broken("matplotlib", "no PNG plots (the CSVs and summary.json are written)"):
            plots = False
        if sweep_list:
            _skip_broken("pyoctomap", "the --sweep times NDT-OM and its floor but not OctoMap")
        folder = _out_folder(out, "the experiments' CSVs, plots and summary.json")
        check_writable(folder / "summary.json", "summary file", option="--out")
        init_taichi(arch)
        try:
            with _recording_errors("experiments"):
                summary = ex.run_experiments(
                    source,
                    resolution,
                    folder,
                    every=every,
                    max_scans=max_scans,
                    sensor_frame_only=sensor_frame,
                    coarsen=coarsen,
                    sweep=sweep_list,
                    sim_scans=sim_scans,
                    sim_stride=sim_stride,
                    tools_dir=simworld,
                    plots=plots,
                    progress=lambda msg: console_err().print(Text(msg, style="cyan")),
                )
        except ValueError as exc:
            _too_fine(exc, "--sweep" if getattr(exc, "what", None) == "sweep" else "-r")
            raise
        except (KeyboardInterrupt, MapMemoryError) as exc:
            stops.phase = "writing"
            _experiments_stopped(exc, folder, stops)
        if summary.get("frame_origin") is not None:
            console_err().print(Text(f"note: {summary['frame_origin_note']}", style="dim"), soft_wrap=True)
        console_out().print(format_summary(summary), soft_wrap=True, markup=False, highlight=False)
        console_out().print(
            f"Wrote {folder / 'summary.json'} and the {'CSVs and figures' if plots else 'CSVs'} in {folder}",
            soft_wrap=True,
            markup=False,
        )


def _experiments_stopped(exc: BaseException, folder: Path, stops) -> None:
    """What an experiments run that stopped early wrote, and the exit code (never returns)."""
    import json

    from ..evaluation.report import format_summary
    from ..evaluation.stops import written_before

    written = written_before(exc)
    signal_stop = isinstance(exc, KeyboardInterrupt)
    if not written:
        if signal_stop:
            fail(
                f"interrupted ({stops.name}) before the main figures were done; nothing was written",
                None,
                stops.exit_code,
            )
        fail(
            _memory_text(exc),
            "use a coarser -r, fewer scans (--every, --max-scans), or a CUDA device (--arch cuda)",
            EXIT_FAILURE,
        )
    try:
        summary = json.loads((folder / "summary.json").read_text())
        console_out().print(format_summary(summary), soft_wrap=True, markup=False, highlight=False)
    except (OSError, ValueError, KeyError, TypeError):
        summary = {}
    fig5 = summary.get("fig5") or {}
    where = f" at {fig5['stopped_at']:g} m" if "stopped_at" in fig5 else ""
    what = (
        f"wrote {folder / 'summary.json'} (complete = false: the Fig. 5 sweep{where} is not finished"
        + (", fig5_sweep.csv holds its rows finished" if fig5.get("rows") else "")
        + f") and {', '.join(p.name for p in written if p.name != 'summary.json')} in {folder}"
    )
    if signal_stop:
        console_err().print(
            Text(f"Interrupted ({stops.name}) during the Fig. 5 sweep: {what}", style="bold yellow"), soft_wrap=True
        )
        raise typer.Exit(stops.exit_code)
    at = fig5.get("stopped_at")
    fail(
        f"--sweep: {'at ' + format(at, 'g') + ' m ' if at else ''}the map does not fit in memory: {_memory_text(exc)}; "
        + what,
        (f"drop {at:g} from --sweep or use coarser ones" if at else "use coarser --sweep resolutions")
        + ", use fewer scans (--every, --max-scans), or a CUDA device (--arch cuda)",
        EXIT_FAILURE,
    )
