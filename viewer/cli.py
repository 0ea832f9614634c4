"""What ``ndtom view`` (and a live-mapping command) call; the Typer CLI stays in ndtom_ti.cli.

Exit codes are the command's (:mod:`ndtom_ti.exitcodes`): 0 done (Ctrl-C is the normal
way to close the viewer); 1 failed (viser missing, the map could not be drawn, a snapshot
that could not be written); 2 bad input (missing or corrupt map file, host that cannot be
listened on, snapshot folder missing); 130 (Ctrl-C) or 143 (SIGTERM) live mapping interrupted
(what was mapped is saved).
"""

from __future__ import annotations

import contextlib
import inspect
import math
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ndtom_ti.atomic import kept_kind
from ndtom_ti.exitcodes import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from ndtom_ti.signals import LiveSignals

from ._deps import ViewerNotInstalledError, require_viser
from .server import listen_port

if TYPE_CHECKING:
    from ndtom_ti.io import ScanSelection

__all__ = ["live_command", "live_demo_command", "live_recording_command", "view_command"]

LISTEN_HINT = (
    "use --host 127.0.0.1 (this machine only) or an address of this machine, and a --port in 0..65535 "
    "(0: any free port)"
)


def _error(message: str, hint: str | None = None) -> None:
    print(f"Error: {message}", file=sys.stderr, flush=True)
    if hint:
        print(f"Hint: {hint}", file=sys.stderr, flush=True)


def _block(viewer: Any) -> None:
    """Serve until Ctrl-C (tests replace this)."""
    viewer.wait()


def _load(path: Path, what: str = "map") -> Any:
    """The map at ``path`` as a snapshot (numpy: no map slot), or None after printing why
    it cannot be read."""
    from ndtom_ti import MapFileError
    from ndtom_ti.snapshot import MapSnapshot

    path = Path(path)
    if not path.exists():
        _error(f"{what} file {path} does not exist", "give a map file written by `ndtom map` or `ndtom demo`")
        return None
    from ndtom_ti.tiledfile import is_tiled, not_tiled

    if path.is_dir() and not is_tiled(path):  # a tiled map's folder (ndtom map --workers --tiled) is a map
        _error(not_tiled(path), "give a map file written by `ndtom map`, or a folder of `ndtom map --tiled`")
        return None
    try:
        return MapSnapshot.load(path)
    except MapFileError as exc:
        _error(f"cannot read {what} file {path}: {exc}", "give a map file written by `ndtom map` or `ndtom demo`")
    except OSError as exc:
        _error(f"cannot read {what} file {path}: {exc.strerror or exc}", "check the path and its permissions")
    except ValueError as exc:  # e.g. cells outside the grid of this build
        _error(f"cannot read {what} file {path}: {exc}")
    return None


def _say(line: str) -> None:
    print(line, flush=True)


@contextlib.contextmanager
def _ticking(what: str, every: float = 10.0) -> Any:
    """Say every ``every`` seconds that ``what`` is still going (big maps take a while)."""
    done = threading.Event()
    t0 = time.perf_counter()

    def tick() -> None:
        while not done.wait(every):
            _say(f"  ... {what} ({time.perf_counter() - t0:.0f} s)")

    th = threading.Thread(target=tick, name="ndtom-view-progress", daemon=True)
    th.start()
    try:
        yield
    finally:
        done.set()
        th.join()


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
        kind = kept_kind(html)
        if kind is not None:
            _error(f"cannot write {html}: {kind}, which writing the page would destroy", "choose another --html path")
            return EXIT_USAGE
        try:  # before the map loads: a folder that takes no file is said at once
            tempfile.TemporaryFile(dir=parent).close()
        except OSError as exc:
            _error(f"cannot write {html}: folder {parent}: {exc.strerror or exc}", "choose another --html path")
            return EXIT_USAGE
    else:
        try:  # before the map loads: a host or port that cannot serve is said at once
            if not 0 <= int(port) <= 65535:
                raise ValueError(f"port must be in [0, 65535], got {port}")
            listen_port(host, int(port))
        except ValueError as exc:
            _error(str(exc), LISTEN_HINT)
            return EXIT_USAGE
    t0 = time.perf_counter()
    path = Path(map_path)
    if path.is_file():
        _say(f"Loading {path} ({path.stat().st_size / 2**20:.1f} MiB) ...")
    try:
        with _ticking("loading"):
            m = _load(path)
    except KeyboardInterrupt:
        _error("interrupted (Ctrl-C) while loading the map")
        return EXIT_INTERRUPTED
    if m is None:
        return EXIT_USAGE
    _say(
        f"Loaded {len(m):,} Gaussian{'' if len(m) == 1 else 's'} at {m.resolution:g} m in {time.perf_counter() - t0:.1f} s"
    )
    cmp_map = None
    if compare is not None:
        cmp_map = _load(Path(compare), "comparison map")
        if cmp_map is None:
            return EXIT_USAGE

    from .app import MapViewer

    try:  # (Ctrl-C while the scene is prepared: no traceback)
        # a snapshot needs no server beyond this machine, and is lit by plain lights: it draws at
        # once (an environment map fades in slowly)
        with _ticking("preparing the scene"):
            viewer = MapViewer(
                m,
                compare=cmp_map,
                host="127.0.0.1" if html is not None else host,
                port=0 if html is not None else port,
                verbose=html is None,
                environment_map=html is None,
                progress=_say,
            )
    except ValueError as exc:
        _error(str(exc), LISTEN_HINT)
        return EXIT_USAGE
    except KeyboardInterrupt:
        _error("interrupted (Ctrl-C) while preparing the scene")
        return EXIT_INTERRUPTED
    if html is not None:
        try:
            viewer.save_html(html)
        except OSError as exc:
            _error(f"cannot write {html}: {exc.strerror or exc}", "the previous file, if any, is unchanged")
            return EXIT_FAILURE
        finally:
            viewer.close()
        _say(
            f"Wrote {html.resolve()} ({html.stat().st_size / 2**20:.1f} MiB): open it in a browser "
            f"({html.resolve().as_uri()})"
        )
        return EXIT_OK
    print("Press Ctrl-C to stop.", flush=True)
    try:
        _block(viewer)
    finally:
        viewer.close()
    return EXIT_OK


# ---------------------------------------------------------------------------- live mapping
def parse_rate(text: str) -> float | None:
    """``--rate``: a positive factor of the recording's rate, or ``max`` (None: no pacing)."""
    t = str(text).strip().lower()
    if t in ("max", "inf", "fastest"):
        return None
    try:
        v = float(t.rstrip("x"))
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        raise ValueError(
            f"--rate must be a positive number (1: the recording's own rate, 2: twice as fast) or max, got {text!r}"
        )
    return v


def _wait_for_browser(viewer: Any, stop: threading.Event) -> bool:
    """Block until a browser shows the viewer (True) or a stop signal came (False)."""
    while not viewer.server.get_clients():
        if stop.wait(0.1):
            return False
    return True


def _serve_until_stopped(viewer: Any, stop: threading.Event) -> None:
    """After mapping: keep serving the final map until Ctrl-C or SIGTERM (tests replace this)."""
    stop.wait()


def _default_finish(save: Path | None) -> Callable[..., int]:
    def finish(m: Any, summary: Any, signals: Any = None) -> int:
        if save is not None and summary.scans_used:
            m.save(save)
            print(f"Wrote {save} ({summary.scans_used} scans)", flush=True)
        if summary.stopped == "interrupted":
            return signals.exit_code if signals is not None and signals.count else EXIT_INTERRUPTED
        return EXIT_FAILURE if summary.stopped == "error" else EXIT_OK

    return finish


def _call_finish(finish: Callable[..., int], m: Any, summary: Any, signals: LiveSignals) -> int:
    """``finish(m, summary)``, given the stop signals too when it takes them (``signals=``:
    which signal stopped mapping names the stop and sets the exit code, 130 or 143)."""
    try:
        takes = "signals" in inspect.signature(finish).parameters
    except (TypeError, ValueError):
        takes = False
    return finish(m, summary, signals=signals) if takes else finish(m, summary)


def live_command(
    scans: Iterable[Any],
    resolution: float,
    host: str = "127.0.0.1",
    port: int = 8080,
    *,
    compare: bool = True,
    config: Any = None,
    occupancy: bool = True,
    total: int | None = None,
    speed: float | None = 1.0,
    rate_hz: float = 0.0,
    wait_for_browser: bool = True,
    save: Path | None = None,
    summary: Any = None,
    metadata: dict | None = None,
    progress: Callable[[Any, Any], None] | None = None,
    finish: Callable[[Any, Any], int] | None = None,
    after_loop: Callable[[], None] | None = None,
) -> int:
    """Map ``scans`` live in the viewer (objects with ``.points``/``.T_world_sensor`` and,
    for pacing, ``.stamp_ns``, e.g. ``Recording.scans(...)``).

    Builds an NDT-OM map (and with ``compare`` a Recursive NDT map beside it) while
    serving: prints the URL, waits for the first browser (unless ``wait_for_browser`` is
    False), then plays at ``speed`` x the recording's rate (None: as fast as mapping
    goes). ``progress(summary, report)`` is called before the first scan (report None)
    and after each, as by ``ndtom map``. At the end, and on Ctrl-C or SIGTERM (after the
    scan in hand), ``finish(map, summary)`` saves the map and prints the summary (the
    default writes ``save``) and returns the exit code; after a complete run the viewer
    keeps showing the map until Ctrl-C. Returns the exit code: ``finish``'s, 130 when
    stopped before any scan, 1 when the viewer could not start or mapping failed.
    """
    try:
        require_viser()
    except ViewerNotInstalledError as exc:
        _error(str(exc))
        return EXIT_FAILURE
    from ndtom_ti import NdtOmMap
    from ndtom_ti.pipeline import MappingSummary, config_with_ranges

    from .app import MapViewer

    cfg = config_with_ranges(config)
    if summary is None:
        summary = MappingSummary(
            source="scans",
            resolution=float(resolution),
            occupancy=bool(occupancy),
            config=cfg.to_dict(),
            scans_expected=total,
        )
    finish = finish or _default_finish(save)
    m = NdtOmMap(resolution, occupancy=occupancy, config=cfg, metadata=summary.metadata(metadata))
    try:
        viewer = MapViewer(m, host=host, port=port, progress=_say)
    except ValueError as exc:
        _error(str(exc), LISTEN_HINT)
        return EXIT_USAGE

    code = EXIT_OK
    lm = None
    try:
        with LiveSignals() as sig:
            lm = viewer.live(
                scans,
                m,
                compare=compare,
                play=False,
                total=total or summary.scans_expected,
                speed=speed if speed is not None else math.inf,
                rate_hz=rate_hz,
                summary=summary,
                progress=progress,
                after_loop=after_loop,
            )
            started = True
            if wait_for_browser:
                _say(
                    f"Waiting for a browser at {viewer.url} (mapping starts when one connects; --no-wait starts "
                    "at once) ..."
                )
                started = _wait_for_browser(viewer, sig.event)
            if started:
                if progress is not None:
                    progress(summary, None)
                lm.play()
                while not lm.wait(0.2) and not sig.event.is_set():
                    pass
            lm.stop()  # after the scan in hand
            exc = lm.exception
            if not (lm.finished and exc is None) and after_loop is not None:  # the loop did not count the clouds
                after_loop()
            summary.clouds_seen = max(summary.clouds_seen, summary.scans_used)
            if exc is not None:  # not a bad scan mid-run (the loop stops at those): mapping failed
                summary.stopped, summary.error = "error", f"{type(exc).__name__}: {exc}"
            elif summary.stopped is None and not lm.completed:
                summary.stopped = "interrupted"
                summary.error = f"interrupted after {summary.scans_used} scans"
            sig.saving = True
            with viewer.map_lock:  # the viewer's threads read the map meanwhile
                summary.count_map(m)
                summary.record_in(m)
                code = _call_finish(finish, m, summary, sig)
            sig.saving = False
            if exc is not None:
                _error(
                    f"live mapping stopped at scan {summary.scans_used + 1}: {summary.error}",
                    f"the {summary.scans_used} scans before it are in the map" if summary.scans_used else None,
                )
                code = EXIT_USAGE if isinstance(exc, (ValueError, TypeError, LookupError)) else EXIT_FAILURE
            if summary.stopped is None and not sig.count:
                _say(f"Mapping done; the viewer keeps showing the map at {viewer.url}: Ctrl-C to quit.")
                sig.serving = True
                _serve_until_stopped(viewer, sig.event)
    finally:
        if lm is not None:
            lm.stop()
        viewer.close()
    return code


def live_recording_command(
    bag: Path,
    resolution: float,
    *,
    selection: ScanSelection,
    occupancy: bool = True,
    config: Any = None,
    metadata: dict | None = None,
    **live: Any,
) -> int:
    """``ndtom map BAG --view``: the recording's scans (``selection``, as for
    ``Recording.scans``) mapped live; the summary and metadata are those of ``ndtom map``.
    Raises RecordingError / ValueError for a recording that cannot be mapped."""
    from ndtom_ti.pipeline import config_with_ranges, open_recording_run

    cfg = config_with_ranges(config)
    with open_recording_run(bag, resolution, selection, occupancy=occupancy, config=cfg, metadata=metadata) as run:
        # no Recursive NDT map beside it by default: a recording's map costs what `ndtom map` costs
        live.setdefault("compare", False)
        return live_command(
            run.stream,
            resolution,
            occupancy=occupancy,
            config=cfg,
            summary=run.summary,
            metadata=run.extra,
            after_loop=run.count_clouds,
            **live,
        )


def live_demo_command(
    host: str = "127.0.0.1",
    port: int = 8080,
    *,
    resolution: float = 0.2,
    n_scans: int = 40,
    speed: float | None = 1.0,
    scans: list | None = None,
    **live: Any,
) -> int:
    """The built-in demo room (``ndtom_ti.demo``) mapped live, NDT-OM beside Recursive NDT
    (``scans``: made here when not given); ``live`` as for :func:`live_command` (``save``
    or ``finish`` writes the map)."""
    from ndtom_ti.demo import make_scans
    from ndtom_ti.pipeline import MappingSummary

    scans = scans if scans is not None else make_scans(n_scans)
    summary = MappingSummary(
        source="ndtom demo (synthetic room)",
        pose_source="exact (synthetic)",
        fixed_frame="world",
        resolution=float(resolution),
        scans_expected=len(scans),
    )
    return live_command(
        scans, resolution, host, port, compare=True, total=len(scans), speed=speed, summary=summary, **live
    )
