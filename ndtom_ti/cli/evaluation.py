"""``ndtom sweep`` (time per scan against resolution beside OctoMap, the paper's Fig. 5)
and ``ndtom experiments`` (the paper's Figs. 1-5): options and tables; the work is
:mod:`ndtom_ti.evaluation`'s."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.text import Text

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
    resolution_list,
    resolution_option,
    user_errors,
    without_extra,
)
from .root import app


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
    out: Annotated[Path, typer.Option("--out", help="Folder for sweep.csv and sweep.png.")] = Path("ndtom_sweep"),
) -> None:
    """Time per scan against resolution (the paper's Fig. 5): NDT-OM, its floor mode and
    optionally OctoMap on the same scans, after a warm-up. Writes CSV, PNG and a table."""
    from ..evaluation import sweep as sw

    with user_errors(recording="`ndtom info BAG` shows what a recording holds"):
        res = resolution_list(resolutions, "--resolutions")
        if (bag is None) == (not synthetic):
            fail("give either a recording BAG or --synthetic", "e.g. `ndtom sweep --synthetic --scans 10`")
        if baseline not in (None, "octomap"):
            fail(f"unknown baseline {baseline!r}", "the supported baseline is `--baseline octomap`")
        if baseline == "octomap":
            need_extra("pyoctomap", "the OctoMap baseline (--baseline octomap)")
        no_plot = without_extra("matplotlib", "the sweep writes sweep.csv and the table but no sweep.png")
        out = output_folder(out, "sweep.csv and sweep.png")
        check_writable(out / "sweep.csv", "CSV file")
        used = init_taichi(arch)
        if synthetic or bag is None:  # one of the two, checked above
            from .. import demo as demo_scene

            data = demo_scene.make_scans(scans, per_ring=1800)
            name = "synthetic room"
        else:
            from ..io import open_recording

            with open_recording(bag) as rec:
                data = list(rec.scans(max_scans=scans, every=every, sensor_frame_only=sensor_frame))
            name = bag.name
            if not data:
                fail(f"no scans with poses in {bag}", "`ndtom info BAG` shows the pose sources")
        rows = sw.run_sweep(
            data, res, floor=floor, baseline=baseline, progress=lambda msg: console_err().print(Text(msg, style="cyan"))
        )
        tags = {**sw.machine_tags(used), "data": name}  # the rows hold the number of scans
        csv_path = sw.write_csv(rows, out / "sweep.csv", tags)
        png_path = (
            None
            if no_plot
            else sw.plot(rows, out / "sweep.png", f"{name}: {len(data)} scans, {used}, {tags['cores']} cores")
        )
        t = make_table(
            f"Sweep: {name}, {len(data)} scans of {sum(len(s.points) for s in data) // len(data):,} points, {used}",
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
        wrote = f"Wrote {csv_path} and {png_path}" if png_path else f"Wrote {csv_path} (no plot: matplotlib missing)"
        console_out().print(wrote, soft_wrap=True, markup=False)


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
    out: Annotated[Path, typer.Option("--out", help="Folder for CSVs, PNGs and summary.json.")] = Path(
        "ndtom_experiments"
    ),
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

    with user_errors(recording="`ndtom info BAG` shows what a recording holds"):
        resolution = resolution_option(resolution)
        sweep_list = resolution_list(sweep_res, "--sweep") if sweep_res else None
        if source.startswith("sim:"):
            try:
                find_simworld(simworld)
            except FileNotFoundError as exc:
                fail(str(exc), "give it with --simworld PATH")
        if plots and without_extra("matplotlib", "no PNG plots (the CSVs and summary.json are written)"):
            plots = False
        if sweep_list:
            without_extra("pyoctomap", "the --sweep times NDT-OM and its floor but not OctoMap")
        out = output_folder(out, "the experiments' CSVs, plots and summary.json")
        check_writable(out / "summary.json", "summary file")
        init_taichi(arch)
        summary = ex.run_experiments(
            source,
            resolution,
            out,
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
        console_out().print(format_summary(summary), soft_wrap=True, markup=False, highlight=False)
        console_out().print(
            f"Wrote {out / 'summary.json'} and the {'CSVs and figures' if plots else 'CSVs'} in {out}",
            soft_wrap=True,
            markup=False,
        )
