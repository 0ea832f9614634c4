"""One exact map built by several worker processes (Ray actors, or in this process).

:class:`TiledMap` shares a map's cells among workers in cubic tiles; every worker sees
every scan and updates its own cells; the result equals the one-process map bit for bit.
See docs/large-maps.md.
"""

from .engines import WorkerLost
from .tiled import TiledMap
from .tiling import Tiling

__all__ = ["TiledMap", "Tiling", "WorkerLost"]
