"""Web viewer for NDT-OM maps (optional extra ``viewer``: ``pip install -e ".[viewer]"`` in the repository).

Importing this package does not need viser; making a viewer does::

    import ndtom_ti
    from ndtom_ti.viewer import show

    s = ndtom_ti.MapSnapshot.load("site.ndtom")   # a map file: no map slot (or show(m) of a map)
    viewer = show(s)            # prints the URL (loopback, a free port); viewer.server is viser's
    viewer.wait()               # until Ctrl-C (in a notebook: leave it running)

Live mapping (a worker thread inserts scans; the viewer redraws, throttled)::

    from ndtom_ti.viewer import MapViewer
    viewer = MapViewer(port=8080)
    live = viewer.live(scans, ndtom_ti.NdtOmMap(0.2), compare=True, play=True)

The CLI (``ndtom view``) calls :func:`ndtom_ti.viewer.cli.view_command`.
"""

from ._deps import ViewerNotInstalledError as ViewerNotInstalledError
from ._deps import require_viser as require_viser
from .app import MapViewer as MapViewer
from .app import show as show
from .live import LiveMapper as LiveMapper

__all__ = ["LiveMapper", "MapViewer", "ViewerNotInstalledError", "require_viser", "show"]
