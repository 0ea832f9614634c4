"""ndtom_ti: exact NDT Occupancy Maps (Saarinen et al., ICRA 2013) with Taichi kernels.

No Taichi field or kernel is created at import time: ``init`` (or the first map) does it.
"""

import os as _os
import typing as _typing

# Taichi prints a version banner on import; a mapping library should not.
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
# Taichi's init asks its server for a newer release (a POST with a machine id, once a day, on
# a thread): a mapping process makes no network call of its own accord. Set it to OFF to allow.
_os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")

from . import taichi_import as _taichi_import  # before anything imports Taichi

_taichi_import.install()

from .config import MapConfig as MapConfig
from .kernels.layout import Layout as Layout
from .map import NdtOmMap as NdtOmMap
from .map import ScanReport as ScanReport
from .mapfile import MapFileError as MapFileError
from .runtime import MapMemoryError as MapMemoryError
from .runtime import NoFreeSlotError as NoFreeSlotError
from .runtime import current_arch as current_arch
from .runtime import init as init
from .snapshot import MapSnapshot as MapSnapshot

if _typing.TYPE_CHECKING:  # at run time imported on first use (__getattr__)
    from .evaluation import metrics as metrics
    from .evaluation import quality as quality

__version__ = "0.1.0"
__all__ = [
    "Layout",
    "MapConfig",
    "MapFileError",
    "MapMemoryError",
    "MapSnapshot",
    "NdtOmMap",
    "NoFreeSlotError",
    "ScanReport",
    "current_arch",
    "init",
    "metrics",
    "quality",
]


_EVALUATION = ("metrics", "quality")  # ndtom_ti.metrics, ndtom_ti.quality (docs/api.md)


def __getattr__(name: str):
    """Submodules named in the docs (``ndtom_ti.pipeline.map_recording``,
    ``ndtom_ti.export.export_file``, ``ndtom_ti.io``, ...) reachable after ``import ndtom_ti``
    alone, imported on first use (rosbags and the exporters stay out of a plain import)."""
    import importlib
    import importlib.util

    if name in _EVALUATION:  # (not imported by a plain import: ~35 ms)
        return importlib.import_module(f"{__name__}.evaluation.{name}")
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
