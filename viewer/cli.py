"""What ``ndtom view`` (and a live-mapping command) call; the Typer CLI stays in ndtom_ti.cli.

Exit codes follow the CLI's: 0 done (Ctrl-C is the normal way to close the viewer);
1 failed (viser missing, the map could not be drawn); 2 bad input (missing or corrupt
map file, host that cannot be listened on, snapshot path that cannot be written).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ._deps import ViewerNotInstalledError, require_viser

__all__ = ["live_command", "live_demo_command", "view_command"]

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


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


def _say(line: str) -> None:
    print(line, flush=True)


def view_command(
    map_path: Path,
    host: str = "127.0.0.1",
    port: int = 8080,
    html: Path | None = None,
    *,
    compare: Path | None = None,
) -> int:
    """``ndtom view MAP [--host 127.0.0.1] [--port N] [--html snapshot.html] [--compare RNDT_MAP]``.

    Says what it does while a big map loads, then serves the map and prints its URL
    (with the real port: a busy port is replaced by the next free one; beyond loopback
    with its access token, after a warning) until Ctrl-C. With ``html`` it writes a
    standalone page of the scene instead (atomically), says where, and returns.
    ``compare``: a map of the same scans built with ``occupancy=False`` (shows the
    conflicting cells).
    """
    try:
        require_viser()
    except ViewerNotInstalledError as exc:
        _error(str(exc))
        return EXIT_FAILURE
    if html is not None:
        html = Path(html).expanduser()
        parent = html.parent if str(html.parent) else Path(".")
        if not parent.is_dir():
            _error(f"cannot write {html}: folder {parent} does not exist", "create the folder first")
            return EXIT_USAGE
        if html.exists() and not html.is_file():
            _error(f"cannot write {html}: it exists and is not a regular file", "choose another --html path")
            return EXIT_USAGE
    t0 = time.perf_counter()
    path = Path(map_path)
    if path.is_file():
        _say(f"Loading {path} ({path.stat().st_size / 2**20:.1f} MiB) ...")
    m = _load(path)
    if m is None:
        return EXIT_USAGE
    _say(f"Loaded {len(m):,} Gaussians at {m.resolution:g} m in {time.perf_counter() - t0:.1f} s")
    cmp_map = None
    if compare is not None:
        cmp_map = _load(Path(compare), "comparison map")
        if cmp_map is None:
            return EXIT_USAGE

    from .app import MapViewer

    try:
        # a snapshot needs no server beyond this machine, and is lit by plain lights: it draws at
        # once (an environment map fades in slowly)
        viewer = MapViewer(m, compare=cmp_map, host="127.0.0.1" if html is not None else host,
                           port=0 if html is not None else port, verbose=html is None,
                           environment_map=html is None, progress=_say)  # fmt: skip
    except ValueError as exc:
        _error(str(exc), "use --host 127.0.0.1 (this machine only) or an address of this machine, "
               "and a --port in 0..65535 (0: any free port)")
        return EXIT_USAGE
    if html is not None:
        try:
            viewer.save_html(html)
        except OSError as exc:
            _error(f"cannot write {html}: {exc.strerror or exc}", "the previous file, if any, is unchanged")
            return EXIT_FAILURE
        finally:
            viewer.close()
        _say(f"Wrote {html.resolve()} ({html.stat().st_size / 2**20:.1f} MiB): open it in a browser "
             f"({html.resolve().as_uri()})")  # fmt: skip
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
) -> int:
    """Map ``scans`` live in the viewer (objects with ``.points``/``.T_world_sensor``, e.g.
    ``Recording.scans(...)``): builds an NDT-OM map (and with ``compare`` a Recursive NDT
    map) while serving, until Ctrl-C; ``save`` writes the NDT-OM map on exit."""
    try:
        require_viser()
    except ViewerNotInstalledError as exc:
        _error(str(exc))
        return EXIT_FAILURE
    from ndtom_ti import NdtOmMap

    from .app import MapViewer

    m = NdtOmMap(resolution, config=config)
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
        lm.stop()
        viewer.close()
        if save is not None:
            m.save(save)
            print(f"Wrote {save} ({lm.scans_done} scans)", flush=True)
    if lm.error:
        _error(f"live mapping stopped: {lm.error}")
        return EXIT_FAILURE
    return EXIT_OK


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
