"""What ``ndtom view`` (and a live-mapping command) call; the Typer CLI stays in ndtom_ti.cli.

Exit codes follow the CLI's: 0 done (Ctrl-C is the normal way to close the viewer;
live mapping stopped by Ctrl-C before its scans ran out: 130, the map saved); 1 failed (viser missing, the map could not be drawn); 2 bad input (missing or corrupt
map file, host that cannot be listened on, snapshot path that cannot be written).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ._deps import ViewerNotInstalledError, require_viser

__all__ = ["live_command", "live_demo_command", "view_command"]

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def _error(message: str, hint: str | None = None) -> None:
    print(f"Error: {message}", file=sys.stderr, flush=True)
    if hint:
        print(f"Hint: {hint}", file=sys.stderr, flush=True)


def _block(viewer: Any) -> None:
    """Serve until Ctrl-C (tests replace this)."""
    viewer.wait()


def _load(path: Path, what: str = "map") -> Any:
    """The map at ``path``, or None after printing why it cannot be read."""
    from ndtom_ti import MapFileError, NdtOmMap

    path = Path(path)
    if not path.exists():
        _error(f"{what} file {path} does not exist", "give a map file written by `ndtom map` or `ndtom demo`")
        return None
    if path.is_dir():
        _error(f"{what} file {path} is a folder, not a map file", "give a map file written by `ndtom map`")
        return None
    try:
        return NdtOmMap.load(path)
    except MapFileError as exc:
        _error(f"cannot read {what} file {path}: {exc}", "give a map file written by `ndtom map` or `ndtom demo`")
    except OSError as exc:
        _error(f"cannot read {what} file {path}: {exc.strerror or exc}", "check the path and its permissions")
    except ValueError as exc:  # e.g. cells outside the grid of this build
        _error(f"cannot read {what} file {path}: {exc}")
    return None


def view_command(
    map_path: Path,
    host: str = "127.0.0.1",
    port: int = 8080,
    html: Path | None = None,
    *,
    compare: Path | None = None,
) -> int:
    """``ndtom view MAP [--host 127.0.0.1] [--port N] [--html snapshot.html] [--compare RNDT_MAP]``.

    Serves the map at ``http://HOST:PORT`` (prints the URL with the real port: a busy
    port is replaced by the next free one) until Ctrl-C; with ``html`` writes a
    standalone page of the scene instead and returns. ``compare``: a map of the same
    scans built with ``occupancy=False`` (shows the conflicting cells).
    """
    try:
        require_viser()
    except ViewerNotInstalledError as exc:
        _error(str(exc))
        return EXIT_FAILURE
    if html is not None:
        html = Path(html)
        parent = html.parent if str(html.parent) else Path(".")
        if not parent.is_dir():
            _error(f"cannot write {html}: folder {parent} does not exist")
            return EXIT_USAGE
    m = _load(Path(map_path))
    if m is None:
        return EXIT_USAGE
    cmp_map = None
    if compare is not None:
        cmp_map = _load(Path(compare), "comparison map")
        if cmp_map is None:
            return EXIT_USAGE

    from .app import MapViewer

    try:
        # a snapshot is lit by plain lights: it draws at once (an environment map fades in slowly)
        viewer = MapViewer(m, compare=cmp_map, host=host, port=0 if html is not None else port,
                           verbose=html is None, environment_map=html is None)  # fmt: skip
    except ValueError as exc:
        _error(str(exc), "use --host 127.0.0.1 (this machine only) or an address of this machine, "
               "and a --port in 0..65535 (0: any free port)")
        return EXIT_USAGE
    if html is not None:
        try:
            viewer.save_html(html)
        except OSError as exc:
            _error(f"cannot write {html}: {exc.strerror or exc}")
            return EXIT_USAGE
        finally:
            viewer.close()
        print(f"Wrote {html} ({html.stat().st_size / 2**20:.1f} MiB): open it in a browser", flush=True)
        return EXIT_OK
    print("Press Ctrl-C to stop.", flush=True)
    try:
        _block(viewer)
    finally:
        viewer.close()
    return EXIT_OK


def live_command(
    scans: Iterable[Any],
    resolution: float,
    host: str = "127.0.0.1",
    port: int = 8080,
    *,
    compare: bool = True,
    config: Any = None,
    total: int | None = None,
    play: bool = True,
    rate_hz: float = 0.0,
    save: Path | None = None,
    metadata: dict | None = None,
) -> int:
    """Map ``scans`` live in the viewer (objects with ``.points``/``.T_world_sensor``, e.g.
    ``Recording.scans(...)``): builds an NDT-OM map (and with ``compare`` a Recursive NDT
    map) while serving, until Ctrl-C; ``save`` writes the NDT-OM map on exit, with
    ``metadata`` and whether every scan was mapped. Returns 0, or 130 when Ctrl-C came
    before the scans ran out (like ``ndtom map``), 1 when mapping failed."""
    try:
        require_viser()
    except ViewerNotInstalledError as exc:
        _error(str(exc))
        return EXIT_FAILURE
    from ndtom_ti import NdtOmMap

    from .app import MapViewer

    m = NdtOmMap(resolution, config=config, metadata=metadata)
    try:
        viewer = MapViewer(m, host=host, port=port)
    except ValueError as exc:
        _error(str(exc), "use --host 127.0.0.1 (this machine only) or an address of this machine")
        return EXIT_USAGE
    lm = viewer.live(scans, m, compare=compare, play=play, total=total, rate_hz=rate_hz)
    print("Press Ctrl-C to stop.", flush=True)
    try:
        _block(viewer)
    finally:
        complete = lm.finished and lm.error is None  # read before stop() ends the scans early
        lm.stop()
        viewer.close()
        if save is not None:
            from ndtom_ti.pipeline import stop_signals

            m.metadata.update(complete=complete, summary={"scans_used": lm.scans_done, "error": lm.error,
                                                          "stopped": None if complete else "error" if lm.error else "interrupted"})
            with stop_signals(phase="saving"):  # a Ctrl-C now waits for the map to be on disk
                m.save(save)
            print(f"Wrote {save} ({lm.scans_done} scans{'' if complete else ', marked incomplete'})", flush=True)
    if lm.error:
        _error(f"live mapping stopped: {lm.error}")
        return EXIT_FAILURE
    return EXIT_OK if complete else EXIT_INTERRUPTED


def live_demo_command(
    host: str = "127.0.0.1",
    port: int = 8080,
    *,
    resolution: float = 0.2,
    n_scans: int = 40,
    rate_hz: float = 4.0,
    play: bool = True,
) -> int:
    """The built-in demo room (``ndtom_ti.demo``) mapped live, NDT-OM beside Recursive NDT."""
    from ndtom_ti.demo import make_scans

    scans = make_scans(n_scans)
    return live_command(scans, resolution, host, port, compare=True, total=len(scans), play=play, rate_hz=rate_hz)
