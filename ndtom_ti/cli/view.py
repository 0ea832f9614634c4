"""``ndtom view``: a map in the browser, or a standalone HTML page of it (the viewer's
side is :func:`ndtom_ti.viewer.cli.view_command`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import Arch, check_not_input, init_taichi, need_extra
from .root import app


# ---------------------------------------------------------------------------- view
@app.command(short_help="Look at a map in the browser, or write an HTML page.")
def view(
    map_file: Annotated[
        Path,
        typer.Argument(
            metavar="MAP",
            help="A map file written by `ndtom map`, or a tiled map's folder (`ndtom map --workers N --tiled DIR`).",
            show_default=False,
        ),
    ],
    host: Annotated[
        str,
        typer.Option(
            help="Address to serve on (default: this machine only; any other address prints a warning and a URL "
            "with an access token)."
        ),
    ] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Port (the next free one if taken; the URL says which).")] = 8080,
    html: Annotated[
        Path | None, typer.Option(help="Write a standalone HTML snapshot of the scene and exit.", show_default=False)
    ] = None,
    compare: Annotated[
        Path | None,
        typer.Option(
            help="A Recursive NDT map (ndtom map --no-occupancy) of the same data: highlights conflicting cells.",
            show_default=False,
        ),
    ] = None,
    arch: Annotated[Arch, typer.Option(help="Taichi backend.")] = Arch.auto,
) -> None:
    """Look at a map in the browser: Gaussians as ellipsoids or splats, occupied and free
    cells, coarser levels, occupancy threshold. Prints the URL; Ctrl-C stops."""
    need_extra("viser", "ndtom view")
    if html is not None:
        check_not_input(html, {"map file": map_file, "comparison map": compare}, "--html")
    from ..viewer.cli import view_command

    init_taichi(arch)
    raise typer.Exit(view_command(map_file, host, port, html, compare=compare))
