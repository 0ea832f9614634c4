"""Measuring maps: the paper's evaluation and the numbers behind it (numpy, plus the maps).

- :mod:`.metrics`: the batch NDT map (eq. 1), the L2 similarity and the mean L2 score;
  also ``ndtom_ti.metrics``.
- :mod:`.quality`: ghosts, static surface kept and conflicting cells of dynamic scenes
  against exact ground truth; also ``ndtom_ti.quality``.
- :mod:`.er_baseline`: the online error-refinement mapper the paper compares against.
- :mod:`.sweep`: time per scan against resolution beside OctoMap (Fig. 5).
- :mod:`.experiments`: :func:`run_experiments`, the paper's Figs. 1-5 on any scans,
  reading them through :mod:`.sources` and writing through :mod:`.report` and
  :mod:`.plots`.

``ndtom experiments`` and ``ndtom sweep`` (:mod:`ndtom_ti.cli.evaluation`) are the
commands over them.
"""

from .experiments import run_experiments as run_experiments
from .report import format_summary as format_summary
from .sources import ScanSet as ScanSet
from .sources import load_scans as load_scans

__all__ = ["ScanSet", "format_summary", "load_scans", "run_experiments"]
