"""``ndtom info`` (what a recording or a map file holds) and ``ndtom export`` (a map file
-> PLY, PCD, npz, CSV, OctoMap .bt or a 2-D occupancy grid, by :mod:`ndtom_ti.export`)."""

from __future__ import annotations

import math
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape as _markup_escape
from rich.text import Text
from rich.tree import Tree

from ..config import SIGMA_S_CELLS, SIGMA_S_MIN
from .common import (
    Arch,
    check_not_input,
    check_writable,
    console_err,
    console_out,
    fail,
    fmt_count,
    fmt_mib,
    fmt_secs,
    frame_origin_text,
    make_table,
    user_errors,
)
from .root import app

_MAGIC = b"NDTOMTI\n"  # the first bytes of a map file


def escape(text: str) -> str:
    """``text`` safe to print: rich markup escaped, and control characters (a terminal's
    escape sequences in a map's metadata or a bag's topic names) shown as \\xNN, not sent."""
    shown = "".join(
        c if c.isprintable() or c == " " else f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}"
        for c in str(text)
    )
    return _markup_escape(shown)


class Format(str, Enum):
    ply = "ply"
    pcd = "pcd"
    npz = "npz"
    csv = "csv"
    bt = "bt"
    grid = "grid"


# ---------------------------------------------------------------------------- info
def _info_map(path: Path) -> None:
    from ..mapfile import read_header

    _info_header(f"Map file {path}", read_header(path))


def _info_tiled(folder: Path) -> None:
    """A tiled map's folder: its manifest, and the header of the map its tiles join into
    (the tiles' headers added up; no cells read)."""
    from ..mapfile import read_header
    from ..tiledfile import read_manifest

    doc = read_manifest(folder)
    if not doc["tiles"]:
        fail(f"{folder} is a tiled map of {doc['scans']} scans without a known cell yet", "map more scans into it")
    heads = [read_header(folder / name) for name in doc["tiles"]]
    h = dict(heads[0])
    rows: dict[str, list] = {}
    for head in heads:
        for a in head.get("arrays", []):
            rows.setdefault(a["name"], [0, *a["shape"][1:]])[0] += int(a["shape"][0])
    h["arrays"] = [{"name": name, "shape": shape} for name, shape in rows.items()]
    h["metadata"] = {**(h.get("metadata") or {}), "complete": bool(doc.get("complete"))}
    state = "complete" if doc.get("complete") else "a checkpoint of a run not finished (ndtom map --resume)"
    tiled = (
        f"{len(doc['tiles'])} tiles of {float(doc.get('tile_size', 0.0)):g} m ({doc['tile_cells']} cells) "
        f"from {doc['workers']} workers, {state}; "
        "`ndtom merge` joins them into one map file"
    )
    _info_header(f"Tiled map {folder}", h, [("tiled map", tiled)])


def _info_header(title: str, h: dict, first: list[tuple[str, str]] | None = None) -> None:
    from ..mapfile import COMPACT_VERSION  # (loaded already: the header was read through it)

    out = console_out()
    t = make_table(title, "", "", header=False)
    for key, text in first or []:
        t.add_row(key, escape(text))
    md = h.get("metadata") or {}
    version = h.get("version")
    stored = (
        " (compact: Gaussians rounded, means to res/131070, scatter to float32)" if version == COMPACT_VERSION else ""
    )
    t.add_row("format version", escape(f"{version}{stored}"))
    t.add_row("resolution", escape(f"{h.get('resolution')} m"))
    t.add_row("occupancy", escape(str(h.get("occupancy"))))
    t.add_row("scans inserted", fmt_count(int(h.get("scans_inserted", 0))))
    t.add_row("points inserted", fmt_count(int(h.get("points_inserted", 0))))
    arrays = {a["name"]: a["shape"] for a in h.get("arrays", [])}
    if "g_index" in arrays:  # one word for one thing: "Gaussians" as `ndtom map` and export count them
        min_points = (h.get("config") or {}).get("min_points", 3)
        summary = md.get("summary")
        gaussians = summary.get("gaussians") if isinstance(summary, dict) else None
        if isinstance(gaussians, int):
            t.add_row("Gaussians", f"{fmt_count(gaussians)} (cells of >= {min_points} points, occupied)")
        t.add_row(
            "Gaussian records",
            f"{fmt_count(arrays['g_index'][0])} (every cell with points: the Gaussians, and "
            f"those of fewer points or in free cells)",
        )
    if "occ_index" in arrays:
        t.add_row("known cells", fmt_count(arrays["occ_index"][0]))
    for key in ("source", "cloud_topic", "pose_source", "ndtom_ti_version", "created", "complete"):
        if key in md:
            t.add_row(key.replace("_", " "), escape(str(md[key])))
    if md.get("frame_origin") is not None:
        t.add_row("frame origin", escape(frame_origin_text(md["frame_origin"])))
    t.add_row("config", escape(", ".join(f"{k}={_config_value(k, v)}" for k, v in (h.get("config") or {}).items())))
    out.print(t)


def _config_value(key: str, value: object) -> object:
    # Stored as null: max_range when there is no limit, sigma_s when it is the map's cells.
    if value is None and key == "max_range":
        return "inf"
    if value is None and key == "sigma_s":
        return f"{SIGMA_S_CELLS:g} cells (at least {SIGMA_S_MIN:g} m)"
    return value


def _info_recording(path: Path) -> None:
    from ..io import open_recording

    with open_recording(path) as rec:
        info = rec.info()
    out = console_out()
    head = make_table(f"Recording {info.path}", "", "", header=False)
    head.add_row("format", f"{info.format.upper()} ({info.storage})")
    head.add_row("messages", fmt_count(info.message_count))
    head.add_row("duration", f"{info.duration_s:.3f} s")
    head.add_row(
        "start / end",
        f"{info.start_ns / 1e9:.3f} / {info.end_ns / 1e9:.3f} s (record time; times below are seconds from the start)",
    )
    out.print(head)

    pose_topics = {s.name for s in info.pose_sources if s.kind == "topic"}
    topics = make_table("Topics", "topic", "type", "messages", "rate", "use")
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
        topics.add_row(escape(ts.name), escape(ts.msgtype), fmt_count(ts.count), rate, escape(use))
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
                    label = (
                        f"{child}  [{e.count} transforms, {fmt_secs(e.first_ns, info.start_ns)} .. "
                        f"{fmt_secs(e.last_ns, info.start_ns)} s]"
                    )
                add(node.add(escape(label)), child)

        for root in roots:
            add(tree.add(escape(root)), root)
        out.print(tree)
    else:
        out.print("TF frames: none (no /tf or /tf_static)")

    ps = make_table("Pose sources", "kind", "source", "parent -> child", "poses", "time span (s)", "note")
    for s in info.pose_sources:
        span = (
            "static"
            if s.first_ns is None
            else f"{fmt_secs(s.first_ns, info.start_ns)} .. {fmt_secs(s.last_ns, info.start_ns)}"
        )
        note = "constant (not a trajectory)" if s.constant and s.count > 1 else ""
        ps.add_row(
            s.kind,
            escape(s.name),
            escape(f"{s.parent_frame} -> {s.child_frame or '?'}"),
            fmt_count(s.count),
            span,
            note,
        )
    if not info.pose_sources:
        ps.add_row("-", "(none)", "", "", "", "")
    out.print(ps)

    m = make_table("Mapping", "", "", header=False)
    m.add_row("mappable topics", escape(", ".join(info.mappable_topics) or "(none)"))
    if info.default_cloud_topic:
        m.add_row("cloud topic", escape(info.default_cloud_topic))
    if info.pose_source:
        m.add_row("poses", escape(info.pose_source))
    out.print(m)
    if info.pose_error:
        out.print(
            Text.assemble(("Cannot map with the defaults: ", "bold yellow"), (info.pose_error, "yellow")),
            soft_wrap=True,
        )
    elif info.default_cloud_topic:
        out.print(Text(f"Ready: ndtom map {path} -r 0.2", style="green"), soft_wrap=True)
    for note in info.notes:
        out.print(Text(f"note: {note}", style="dim"), soft_wrap=True)


@app.command(short_help="What a recording (topics, TF tree, poses) or a map file holds.")
def info(
    path: Annotated[
        Path,
        typer.Argument(
            metavar="PATH",
            help="A ROS1 .bag file, a ROS2 bag folder, an .ndtom map file, or a tiled map's folder.",
            show_default=False,
        ),
    ],
) -> None:
    """Show what is in a recording: topics, types, counts, duration, the TF tree, which
    topics can be mapped and which pose sources exist. Given a map file, show its header;
    given a tiled map's folder (``ndtom map --workers N --tiled DIR``), the header of the
    map its tiles join into."""
    # (this command's own hint must not suggest this command again)
    with user_errors(
        recording="`ndtom info` takes a ROS1 .bag file, a ROS2 bag folder (with its metadata.yaml), "
        "an .ndtom map file or a tiled map's folder (with its manifest.json)",
        map_file="give a map file written by `ndtom map` or `ndtom demo` (`ndtom info` also takes recordings)",
    ):
        from ..tiledfile import is_tiled

        if is_tiled(path):  # a tiled map's folder (ndtom map --workers N --tiled DIR)
            _info_tiled(path)
            return
        is_map = path.suffix.lower() == ".ndtom"  # named a map file: its faults are a map file's, not a bag's
        if path.is_file() and not is_map:
            with path.open("rb") as fh:
                is_map = fh.read(len(_MAGIC)) == _MAGIC
        if is_map:
            _info_map(path)
            return
        _info_recording(path)


# ---------------------------------------------------------------------------- export
@app.command(short_help="Write a map as PLY, PCD, npz, CSV, OctoMap .bt or 2-D grid.")
def export(
    map_file: Annotated[
        Path,
        typer.Argument(
            metavar="MAP",
            help="A map file written by `ndtom map`, or a tiled map's folder (`ndtom map --workers N --tiled DIR`).",
            show_default=False,
        ),
    ],
    fmt: Annotated[
        Format | None,
        typer.Option(
            "-f",
            "--format",
            help="ply (Gaussian means coloured by height, with covariances), pcd (means with n and "
            "occupancy, for PCL tools), npz (all arrays), csv (one row per Gaussian), bt (OctoMap tree of occupied and "
            "free cells, for octovis and octomap_server), grid (2-D occupancy grid of a height band: PGM + YAML for "
            "ROS map_server). Default: from the -o suffix (.ply .pcd .npz .csv .bt .pgm .yaml; another suffix is "
            "refused), else ply.",
            show_default=False,
        ),
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option(
            "-o", "--output", help="File to write. Default: MAP with the format's suffix.", show_default=False
        ),
    ] = None,
    min_probability: Annotated[
        float,
        typer.Option(
            help="Occupied means occupancy probability above this (and above 0.5). ply, pcd, npz, csv: export the "
            "Gaussians above it (0: all Gaussians)."
        ),
    ] = 0.5,
    z_min: Annotated[
        float | None,
        typer.Option(
            help="grid: bottom of the height band (m, map frame), with --z-max. Default: the band from 0.3 m (at "
            "least a cell) to 2 m above a floor plane fitted to the map's lowest Gaussians.",
            show_default=False,
        ),
    ] = None,
    z_max: Annotated[
        float | None,
        typer.Option(help="grid: top of the height band (m, map frame), with --z-min.", show_default=False),
    ] = None,
    arch: Annotated[
        Arch, typer.Option(help="Unused: export runs without Taichi (kept for older scripts).", hidden=True)
    ] = Arch.auto,
) -> None:
    """Export a map: its Gaussians (ply, pcd, npz, csv), its cells as an OctoMap tree (bt),
    or a 2-D occupancy grid of a height band (grid: PGM + YAML as ROS map_server reads)."""
    from ..export import DEFAULT_SUFFIX, export_file, format_for, grid_paths

    with user_errors(map_file="give a map file written by `ndtom map` or `ndtom demo`"):
        try:
            fmt_name = format_for(output, fmt.value if fmt is not None else None)
        except ValueError as exc:
            fail(str(exc), "name the format with --format, or use its suffix: e.g. -o map.bt, -o map.pgm")
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
        from ..tiledfile import is_tiled, not_tiled

        if not map_file.exists():
            fail(f"no map file at {map_file}", "give a map file written by `ndtom map` or `ndtom demo`")
        tiled = is_tiled(map_file)  # a tiled map's folder: its tiles joined
        if map_file.is_dir() and not tiled:
            fail(
                not_tiled(map_file),
                "give a map file written by `ndtom map` or `ndtom demo`, or a folder of `ndtom map --tiled`",
            )
        if output is not None:
            out_path = output
        elif tiled:  # beside the folder: site.tiles -> site.tiles.ply
            out_path = map_file.parent / (map_file.name + DEFAULT_SUFFIX[fmt_name])
        else:
            out_path = map_file.with_suffix(DEFAULT_SUFFIX[fmt_name])
        out_path = out_path.expanduser()
        targets = grid_paths(out_path) if fmt_name == "grid" else (out_path,)
        for t in targets:
            check_not_input(t, {"map file": map_file})
        for t in targets:  # a grid's both files: a bad YAML path left the PGM written
            check_writable(t, f"{fmt_name} file", suffix=DEFAULT_SUFFIX[fmt_name])
        from ..snapshot import MapSnapshot

        # a snapshot: numpy only, no map slot and no Taichi (--arch has nothing to choose)
        done = export_file(
            MapSnapshot.load(map_file), out_path, fmt_name, min_probability=min_probability, z_min=z_min, z_max=z_max
        )
        size = sum(p.stat().st_size for p in done.paths)
        size_text = fmt_mib(size) if size >= 2**20 else f"{size / 1024:.1f} KiB"
        console_out().print(Text(f"Exported {done.summary} ({fmt_name}, {size_text})", style="green"), soft_wrap=True)
        for note in done.notes:
            console_err().print(Text(f"note: {note}", style="dim"), soft_wrap=True)
