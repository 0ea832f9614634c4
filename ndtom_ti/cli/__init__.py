"""``ndtom``: map ROS bags into NDT Occupancy Maps, inspect them, export the maps.

Commands, a module each group:

- :mod:`.inspect`: ``info`` (what is in a recording or a map file), ``export`` (map file
  -> PLY, PCD, npz, CSV, OctoMap .bt or a 2-D occupancy grid);
- :mod:`.mapping`: ``map`` (recording -> map file), ``demo`` (a built-in synthetic scene
  -> map file);
- :mod:`.tiles`: ``map --workers N``'s options (a map built by several worker processes on
  Ray) and ``merge`` (a tiled map's folder -> map file);
- :mod:`.evaluation`: ``sweep`` (time per scan against resolution), ``experiments`` (the
  paper's evaluation);
- :mod:`.view`: ``view`` (a map in the browser).

:mod:`.root` holds the Typer app, its root options and :func:`main`; :mod:`.common` the
console, the one-line errors with a hint and the option checks every command shares. The
work is done by :mod:`ndtom_ti.pipeline`, :mod:`ndtom_ti.export`,
:mod:`ndtom_ti.evaluation` and :mod:`ndtom_ti.viewer`; these modules parse options, show
progress and tables, and turn errors into one red line and a hint. Exit codes:
:mod:`ndtom_ti.exitcodes`.
"""

from . import evaluation, inspect, mapping, tiles, view
from .mapping import default_output
from .root import app, main

# `ndtom --help` lists the commands in this order.
_ORDER = ("info", "map", "merge", "demo", "sweep", "experiments", "view", "export")
app.registered_commands.sort(key=lambda c: _ORDER.index(c.name or getattr(c.callback, "__name__", "")))

__all__ = ["app", "default_output", "evaluation", "inspect", "main", "mapping", "tiles", "view"]
